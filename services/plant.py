"""Plant process: MuJoCo at 1 kHz on the bus (see teleop.plant_service)."""

import sys

from teleop.plant_service import PlantService
from teleop.service import service_main


def main() -> int:
    return service_main(PlantService)


if __name__ == "__main__":
    sys.exit(main())
