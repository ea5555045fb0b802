"""``python -m services.sensor_sim``: the simulated robot as its own process."""

import sys

from services.runtime import service_main
from services.sensor_sim.node import SERVICE, add_arguments, main_run

if __name__ == "__main__":
    sys.exit(service_main(SERVICE, main_run, add_arguments=add_arguments,
                          description="Simulated robot: publishes odometry, compass, sonar and ground truth "
                                      "on a simulated clock; takes velocity commands."))
