"""Eye-view process: the scene rendered from the HMD pose, on the bus (see teleop.eyeview)."""

import sys

from teleop.eyeview import EyeViewService
from teleop.service import service_main


def main() -> int:
    return service_main(EyeViewService)


if __name__ == "__main__":
    sys.exit(main())
