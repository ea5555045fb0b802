"""Recorder: a Rerun recording of every map update, the robot, its sensors and the relaxer's progress."""
