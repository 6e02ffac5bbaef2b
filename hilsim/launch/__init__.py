"""Run machinery: starting, supervising and summarising a scenario's processes (``hilsim up``)."""
