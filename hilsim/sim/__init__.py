"""Simulation models: the MuJoCo world, sensors, control laws, kinematics, the scene and tasks."""
