"""A person at the controls: what their device asks of the hand (keys, gamepad,
SpaceMouse, a web page), the loop that paces their hand inputs and reads the task from
the world, and the bus adapter each person's device extends."""
