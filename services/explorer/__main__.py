"""``python -m services.explorer``: the explorer (planner and local controller) as its own process."""

import sys

from services.explorer.node import SERVICE, add_arguments, main_run
from services.runtime import service_main

if __name__ == "__main__":
    sys.exit(service_main(SERVICE, main_run, add_arguments=add_arguments,
                          description="Explorer: predicts and confirms places, plans over the place graph, "
                                      "answers each simulator tick with a velocity command."))
