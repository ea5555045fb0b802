"""dead_reckoning: compass-based and raw odometry from the sensor streams, with gap and order checks."""
