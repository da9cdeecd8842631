"""Transport-floor relay process (controller's place in the chain; see teleop.bench.relay)."""

import sys

from teleop.bench.relay import ControllerRelay
from teleop.bus.service import service_main


def main() -> int:
    return service_main(ControllerRelay)


if __name__ == "__main__":
    sys.exit(main())
