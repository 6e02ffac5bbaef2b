"""Rover navigation: an occupancy grid of the world's static geometry (:mod:`.grid`), OMPL
planning in SE(2) with Reeds–Shepp curves over it (:mod:`.planner`), a path follower that turns
the plan into body twists for ``cmd_vel`` (:mod:`.follower`), and ``hilsim plan evaluate`` for
rover goals (:mod:`.evaluate`). No transport here: the service is ``services/navigator.py``; see
docs/navigation.md."""
