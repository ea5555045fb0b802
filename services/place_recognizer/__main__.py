"""``python -m services.place_recognizer``: place recognition and link measurement as its own process."""

import sys

from services.place_recognizer.node import SERVICE, add_arguments, main_run
from services.runtime import service_main

if __name__ == "__main__":
    sys.exit(service_main(SERVICE, main_run, add_arguments=add_arguments,
                          description="Place recognizer: local sonar histograms matched against every place, "
                                      "a belief over places, link measurements between them."))
