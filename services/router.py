"""A site's Zenoh router, for a run split across hosts (docs/sites.md).

The services of a site are peers of one another (the launcher's mesh) and of their
site's router; the robot site's router listens for the operator site's
(``site.listen``), the operator site's connects to it (``site.connect``), both over
mutual TLS with the run's certificates. The routers forward each stream between the
sites (every stream both ways, under the run's access-control list: each local peer may
still send only its own streams). No Python runs per message: the forwarding is
Zenoh's own; this process opens the session, follows its link to the other site (the
other router's liveliness token) and waits to be stopped.
"""

from __future__ import annotations

import logging
import sys
import threading
from typing import Any

import zenoh

from teleop.bus.graph import router_instance, router_name
from teleop.bus.service import Service, ServiceOptions, service_main
from teleop.bus.session import router_config
from teleop.bus.topics import Topics
from teleop.core.config import SITES, Config, ConfigError

logger = logging.getLogger(__name__)


class RouterService(Service):
    name = "router"  # scheduling and logs; the participant is its site's router_name

    def __init__(self, config: Config, options: ServiceOptions | None = None) -> None:
        super().__init__(config, options)
        if not config.site.name:
            raise ConfigError("the router serves one site of a run across hosts: set site.name")
        self.name = router_name(config.site.name)  # its tokens
        # The site it links to: the operator site's router for a robot site (through the
        # first robot's router, for another robot's site), the first robot's for the
        # operator site.
        other = next(site for site in SITES if site != config.site.name)
        self.other_router = router_name(other)
        if config.site.robot:  # another robot's site: its tokens under its robot's keys
            self.robot_topics = (Topics(config.site.robot),)
        self._lock = threading.Lock()
        self.other_site_linked = False
        self.other_site_links = 0  # times the other site's router came (its token appeared)
        self.other_site_losses = 0  # times it went (its token's DELETE: link cut, or it died)

    @property
    def instance(self) -> str:
        """Its participant (credentials, summary): the site's router, or another robot's
        site's own instance (graph.router_instance)."""
        return router_instance(self.config.site.name, self.config.site.robot)

    def zenoh_config(self) -> zenoh.Config:
        return router_config(self.config.bus, self.config.site, listen=self.options.listen)

    def open(self) -> None:
        super().open()
        assert self.session is not None
        # The other router's liveliness token crosses the link between the sites: it
        # appears when the link comes up and goes when the link is cut, at once (event
        # driven, no polling that could miss a short cut).
        self.keep(
            self.session.liveliness().declare_subscriber(
                self.topics.alive(self.other_router), self._on_other_router, history=True
            )
        )
        self.announce()

    def _on_other_router(self, sample: zenoh.Sample) -> None:
        linked = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            if linked == self.other_site_linked:
                return
            self.other_site_linked = linked
            self.other_site_links += linked
            self.other_site_losses += not linked
        if linked:
            logger.info("linked to the other site's router (%s)", self.other_router)
        else:
            logger.warning("the other site's router is gone: waiting for it to link again")

    def run(self, stop: threading.Event) -> None:
        """The forwarding is Zenoh's; this thread only waits to be stopped."""
        stop.wait()

    def summary(self) -> dict[str, Any]:
        with self._lock:
            links = {
                "other_site_linked": self.other_site_linked,
                "other_site_links": self.other_site_links,
                "other_site_losses": self.other_site_losses,
            }
        return {**super().summary(), "site": self.config.site.name, **links}


if __name__ == "__main__":
    sys.exit(service_main(RouterService))
