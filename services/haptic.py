"""Haptic process: the emulated Falcon-like device on the bus (see teleop.haptic_service)."""

import sys

from teleop.haptic_service import HapticService
from teleop.service import service_main


def main() -> int:
    return service_main(HapticService)


if __name__ == "__main__":
    sys.exit(main())
