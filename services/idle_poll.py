"""Idle poller process: one CPU kept polling while a realtime stack runs (teleop.run.idle_poll)."""

import sys

from teleop.run.idle_poll import main

if __name__ == "__main__":
    sys.exit(main())
