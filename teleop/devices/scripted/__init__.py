"""The scripted operator: the scenario it plays, the decisions of a person it stands
in for, its loop and station on the bus's ticks, and the routes it plans around what it
sees."""
