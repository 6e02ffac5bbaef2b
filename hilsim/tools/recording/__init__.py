"""What a user does with a recording: ``hilsim play`` publishes a recorded bag's samples again in sim
time (:mod:`.play`), ``hilsim export`` turns a run's Rerun recording into CSV files or an MCAP bag
(:mod:`.export`), and ``hilsim bag info|recover|diff`` reads a bag, makes a killed recorder's bag whole
and finds where two bags first differ (:mod:`.bagtool`)."""
