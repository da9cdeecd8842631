"""A site's Zenoh router, for a run split across hosts (docs/sites.md).

The services of a site are peers of one another (the launcher's mesh) and of their
site's router; the robot site's router listens for the operator site's
(``site.listen``), the operator site's connects to it (``site.connect``), both over
mutual TLS with the run's certificates. The routers forward each stream between the
sites (every stream both ways, under the run's access-control list: each local peer may
still send only its own streams). No Python runs per message: the forwarding is
Zenoh's own; this process opens the session, reports its links and waits to be stopped.
"""

from __future__ import annotations

import logging
import sys
import threading
from typing import Any

import zenoh

from teleop.bus.graph import router_name
from teleop.bus.service import Service, ServiceOptions, service_main
from teleop.bus.session import router_config
from teleop.core.config import Config, ConfigError

logger = logging.getLogger(__name__)

# How often the router logs a change of its links to the other site (s).
LINK_CHECK_S = 1.0


class RouterService(Service):
    name = "router"  # scheduling and logs; the participant is its site's router_name

    def __init__(self, config: Config, options: ServiceOptions | None = None) -> None:
        super().__init__(config, options)
        if not config.site.name:
            raise ConfigError("the router serves one site of a run across hosts: set site.name")
        self.name = router_name(config.site.name)  # its credentials, tokens and summary

    def zenoh_config(self) -> zenoh.Config:
        return router_config(self.config.bus, self.config.site, listen=self.options.listen)

    def open(self) -> None:
        super().open()
        self.other_site_links = 0  # times the link to the other site's router came up
        self._linked = False
        self.announce()

    def _routers(self) -> list[str]:
        assert self.session is not None
        return [str(zid) for zid in self.session.info.routers_zid()]

    def run(self, stop: threading.Event) -> None:
        """Log each time the other site's router links or goes, until stopped."""
        while not stop.wait(LINK_CHECK_S):
            linked = bool(self._routers())
            if linked != self._linked:
                self._linked = linked
                self.other_site_links += linked
                if linked:
                    logger.info("linked to the other site's router")
                else:
                    logger.warning("the other site's router is gone: waiting for it")

    def summary(self) -> dict[str, Any]:
        session = self.session
        open_ = session is not None and not session.is_closed()
        return {
            **super().summary(),
            "site": self.config.site.name,
            "other_site_linked": bool(open_ and self._routers()),
            "other_site_links": getattr(self, "other_site_links", 0),
            "site_peers": len(list(session.info.peers_zid())) if open_ else 0,
        }


if __name__ == "__main__":
    sys.exit(service_main(RouterService))
