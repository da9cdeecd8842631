"""Operator process: the scripted operator on the haptic handle (see teleop.operator_service)."""

import sys

from teleop.operator_service import OperatorService
from teleop.service import service_main


def main() -> int:
    return service_main(OperatorService)


if __name__ == "__main__":
    sys.exit(main())
