"""``python -m services.dead_reckoning``: compass-based and raw dead reckoning as its own process."""

import sys

from services.dead_reckoning.node import SERVICE, add_arguments, main_run
from services.runtime import service_main

if __name__ == "__main__":
    sys.exit(service_main(SERVICE, main_run, add_arguments=add_arguments,
                          description="Dead reckoning: heading from the compass, distance from the wheels, "
                                      "and raw odometry side by side."))
