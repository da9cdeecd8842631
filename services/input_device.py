"""A person on a gamepad or a SpaceMouse drives the arm (``teleop run grasp --operator
gamepad|spacemouse``): the operator's place in the stack
(teleop/devices/person/service.py), read from a Linux input device
(teleop/devices/person/input_devices.py: evdev or hidraw, found through sysfs, decoded by
teleop/devices/person/input_events.py).

It runs under supervisord like every service (the device is not the terminal's). Its
loop waits on the device (``poll``, no busy loop) and hands each intent to the pacer; a
gamepad that can rumble renders the force the emulated handle feels
(``gamepad.rumble*``), and the force is in the recording as for every run. A device that
goes away mid-run ends the task (not a success) rather than leaving the hand where it was.
In a run of several robots a press of one of the device's ``switch_buttons`` drives the
next robot, the gripper as the hand last left it.
"""

from __future__ import annotations

import logging
import sys
import threading
import time

from teleop.bus.messages import Button
from teleop.bus.service import service_main
from teleop.devices.person.input_devices import (
    DeviceUnavailable,
    PersonInputDevice,
    open_input_device,
)
from teleop.devices.person.intent import HandIntent
from teleop.devices.person.service import PersonOperatorService

logger = logging.getLogger(__name__)

# The device loop's longest wait for input (s): how soon it sees a stop or renders a new
# force when the person does not move.
READ_TIMEOUT_S = 0.05


class InputDeviceOperatorService(PersonOperatorService):
    """The device is ``run.operator`` (gamepad or spacemouse)."""

    def open(self) -> None:
        self.device = self.config.run.operator
        self.reader: PersonInputDevice = open_input_device(self.device, self.config)
        self._intent = HandIntent()
        self._switch_presses = 0  # the reader's robot-switch presses acted on
        self.device_lost = ""
        super().open()

    def intent(self, now_ns: int) -> HandIntent:
        return self._intent  # the caller holds self.lock

    def interact(self, stop: threading.Event) -> None:
        try:
            while not stop.is_set():
                try:
                    intent = self.reader.read(READ_TIMEOUT_S)
                except DeviceUnavailable as exc:
                    self.device_lost = str(exc)
                    logger.error("%s: ending the task", exc)
                    self.end_task()
                    stop.wait()
                    return
                now_ns = time.monotonic_ns()
                if self.reader.switch_presses > self._switch_presses:  # the robot switch
                    self._switch_presses = self.reader.switch_presses
                    if self.switch_robot():
                        intent = self._intent  # as take_robot left it
                with self.lock:
                    changed = intent != self._intent
                    self._intent = intent
                    force_n = self.loop.view.force_n
                if changed:
                    self.input_changed(now_ns)
                self.reader.rumble(force_n)
        finally:
            self.reader.close()

    def take_robot(self, buttons: Button) -> None:
        self._intent = self.reader.take_robot(buttons)  # the caller holds self.lock

    def summary(self) -> dict[str, object]:
        return {**super().summary(), "device_lost": self.device_lost or None}


if __name__ == "__main__":
    sys.exit(service_main(InputDeviceOperatorService))
