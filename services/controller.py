"""Controller process: path following from the plant's state (see teleop.controller_service)."""

import sys

from teleop.controller_service import ControllerService
from teleop.service import service_main


def main() -> int:
    return service_main(ControllerService)


if __name__ == "__main__":
    sys.exit(main())
