"""The simulated world and robot: floor plans, kinematics, sensor models (pure, no bus)."""
