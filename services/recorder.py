"""Recorder process: every stream of the robot into a Rerun recording (see teleop.recorder)."""

import sys

from teleop.recorder import RecorderService
from teleop.service import service_main


def main() -> int:
    return service_main(RecorderService)


if __name__ == "__main__":
    sys.exit(main())
