"""Idle poller process: one CPU kept polling while a realtime stack runs (see teleop.idle_poll)."""

import sys

from teleop.idle_poll import main

if __name__ == "__main__":
    sys.exit(main())
