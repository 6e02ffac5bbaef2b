"""Planning evaluation and the learned choice: ``hilsim plan evaluate`` plans several targets of a
scenario and compares them (:mod:`.evaluate` dispatches: an arm's joint targets, :mod:`.arm`; a rover's
goals, :mod:`.rover`; planners compared on a scenes file's queries, :mod:`.scenes`; what they share,
:mod:`.common`), and ``hilsim plan learn`` / ``plan scenes`` build the planner choice's data set and
train its model (:mod:`.learn`)."""
