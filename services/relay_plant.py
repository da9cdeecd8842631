"""Transport-floor relay process (plant's place in the chain; see teleop.bench.relay)."""

import sys

from teleop.bench.relay import PlantRelay
from teleop.bus.service import service_main


def main() -> int:
    return service_main(PlantRelay)


if __name__ == "__main__":
    sys.exit(main())
