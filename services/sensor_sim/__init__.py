"""sensor_sim: the simulated robot on the bus (clock, motion, odometry, compass, sonar, ground truth)."""
