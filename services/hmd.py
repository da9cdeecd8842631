"""HMD process: head pose at 90 Hz of sim time, filtered and predicted (see teleop.hmd_service)."""

import sys

from teleop.hmd_service import HmdService
from teleop.service import service_main


def main() -> int:
    return service_main(HmdService)


if __name__ == "__main__":
    sys.exit(main())
