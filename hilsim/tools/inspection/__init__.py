"""Looking at and poking a running simulation: ``hilsim topic list|echo|hz`` reads its topics the way
``ros2 topic`` does, publishing nothing (:mod:`.topic`), and ``hilsim gains`` reads or changes the
controller's gains, checked by the controller's own rule before they are sent (:mod:`.params`)."""
