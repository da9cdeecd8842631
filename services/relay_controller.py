"""Transport-floor relay process (controller's place in the chain; see teleop.relay)."""

import sys

from teleop.relay import ControllerRelay
from teleop.service import service_main


def main() -> int:
    return service_main(ControllerRelay)


if __name__ == "__main__":
    sys.exit(main())
