"""MuJoCo twin of the robot: the MJCF built from the robot description, and the model that steps it."""
