"""A person at a web page drives the arm (``teleop run grasp --operator web``): the
operator's place in the stack (teleop/devices/person/service.py), read from the page of
:mod:`teleop.devices.person.web_page` (its server, endpoints, token and threads are described
there). This adapter ties the page to the bus: the page's input is the hand's intent, its
robot switch the station's, its state the driven robot's world, its view that robot's
eye-view frames.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from teleop.bus.messages import EYE_VIEW, Button
from teleop.bus.service import service_main
from teleop.bus.session import subscribe_frames
from teleop.core.config import ConfigError
from teleop.devices.person.intent import DEFAULT_KEYS, HandIntent
from teleop.devices.person.service import PersonOperatorService
from teleop.devices.person.web_page import (
    PAGE_FILE,
    EyeFrames,
    PageIntent,
    PageServer,
    page_settings,
    read_token,
    render_page,
    state_message,
)

logger = logging.getLogger(__name__)


class WebOperatorService(PersonOperatorService):
    device = "web"

    def open(self) -> None:
        web = self.config.web
        token = read_token(Path(web.token_file))
        page = render_page(PAGE_FILE.read_text(), page_settings(self.config, DEFAULT_KEYS))
        self.page_intent = PageIntent(web.input_expiry_s)
        self.frames = EyeFrames(web.jpeg_quality)
        # Bound before the session opens: a taken port fails the start-up, in one line.
        try:
            self.site = PageServer(web.port, self, token=token, page=page, frames=self.frames,
                                   state_rate_hz=web.state_rate_hz)  # fmt: skip
        except OSError as exc:
            raise ConfigError(f"web.port {web.port}: {exc.strerror}") from None
        super().open()
        assert self.session is not None
        for robot, topics in enumerate(self.robot_topics):  # the driven robot's frames shown
            self.keep(subscribe_frames(self.session, topics.eye_view, EYE_VIEW,
                                       self._frames_of(robot), self.drops))  # fmt: skip
        logger.info("the page is served on http://127.0.0.1:%d/ (token in %s)", self.site.port,
                    web.token_file)  # fmt: skip

    def _frames_of(self, robot: int) -> Callable[[np.ndarray, np.ndarray, int, bool], None]:
        """Robot ``robot``'s eye-view frames into the page's, while the hand drives it."""

        def on_frame(rec: np.ndarray, pixels: np.ndarray, rx_ns: int, via_shm: bool) -> None:
            if self.station.active == robot:
                self.frames(rec, pixels, rx_ns, via_shm)

        return on_frame

    def intent(self, now_ns: int) -> HandIntent:
        return self.page_intent.intent(now_ns)  # the caller holds self.lock

    def interact(self, stop: threading.Event) -> None:
        self.site.serve(stop)

    def close(self) -> None:
        site = getattr(self, "site", None)
        if site is not None:
            site.close()
        super().close()

    # -- what the page asks (teleop.devices.person.web_page.PageOperator; request threads) ------
    def take_input(self, intent: HandIntent, robot: str | None = None) -> None:
        """The page's input, meant for ``robot`` (None: whichever is driven). One for
        another robot than the one driven now is dropped and counted."""
        now_ns = time.monotonic_ns()
        with self.lock:
            other_robot = robot is not None and robot != self.robot_id
            changed = not other_robot and self.page_intent.update(intent, now_ns)
        if other_robot:
            self.site.count("other_robot_inputs")
        elif changed:
            self.input_changed(now_ns)

    def switch_from_page(self) -> dict[str, Any]:
        """The page's robot switch: the next robot driven, the page's held input as the
        hand last left that robot (no motion; its gripper and clutch), and what the page
        is to take up: ``switched``, the ``robot`` driven, its ``gripper`` and ``clutch``."""
        self.site.count("switches")
        switched = self.switch_robot()
        with self.lock:
            out: dict[str, Any] = {"switched": switched, "robot": self.robot_id}
            if switched:
                held = self.page_intent.newest
                out.update(gripper=held.gripper_closed, clutch=held.clutch)
        return out

    def take_robot(self, buttons: Button) -> None:
        self.page_intent.take_robot(buttons)  # the caller holds self.lock

    def state(self) -> dict[str, Any]:
        now_ns = time.monotonic_ns()
        frame_seq = self.frames.newest
        with self.lock:
            return state_message(
                self.loop.view,
                self.config,
                self.page_intent.intent(now_ns),
                intent_live=self.page_intent.live(now_ns),
                run_over=self.run_over.is_set(),
                frame_seq=frame_seq,
                robot_id=self.robot_id,
                settling=self.station.settling,
            )

    def summary(self) -> dict[str, Any]:
        with self.lock:
            inputs, expiries = self.page_intent.inputs, self.page_intent.expiries
        return {
            **super().summary(),
            "web": {
                **self.site.summary(),
                "inputs": inputs,
                "input_expiries": expiries,
                "frames_received": self.frames.received,
                "frames_encoded": self.frames.encoded,
            },
        }


if __name__ == "__main__":
    sys.exit(service_main(WebOperatorService))
