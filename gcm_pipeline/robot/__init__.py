"""Robot models, kinematics, inverse kinematics and manipulability."""
