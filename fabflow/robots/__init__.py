"""Machine models, kinematics, inverse kinematics and robot program writers."""
