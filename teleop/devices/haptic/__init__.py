"""The haptic device: its interface, the emulated handle and its velocity estimator,
the replayed device, the passivity observer and controller, and the loop that drives any
of them (one bus period per plant tick)."""
