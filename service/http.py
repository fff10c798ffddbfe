"""uvicorn's httptools protocol with deadlines for slow clients (slowloris and slow bodies).

uvicorn limits idle keep-alive connections, but not a client that trickles its request headers or
body: such connections were held for minutes.  This protocol gives every request
``header_timeout_s`` from its connection (or from the previous answer) to finish its headers, and
``body_timeout_s`` from then to finish its body; a client that misses either is disconnected.  The
application's own time is not limited here (/exact has its deadline).  The connection cap is
uvicorn's ``limit_concurrency`` (503 beyond it), set by ``tdcr serve`` from the same settings.
"""

from __future__ import annotations

import asyncio
from functools import cache

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from service.settings import Settings


@cache
def _settings() -> Settings:
    return Settings()


class GuardedHttpToolsProtocol(HttpToolsProtocol):
    """``HttpToolsProtocol`` plus header and body deadlines (``TDCR_HEADER_TIMEOUT_S``,
    ``TDCR_BODY_TIMEOUT_S``)."""

    _deadline: asyncio.TimerHandle | None = None

    def _arm(self, seconds: float | None) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
        self._deadline = None if seconds is None else self.loop.call_later(seconds, self._too_slow)

    def _too_slow(self) -> None:
        if not self.transport.is_closing():
            self.transport.close()

    def connection_made(self, transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm(_settings().header_timeout_s)

    def on_headers_complete(self) -> None:
        super().on_headers_complete()
        self._arm(_settings().body_timeout_s)

    def on_message_complete(self) -> None:
        super().on_message_complete()
        self._arm(None)  # the request is in; the application takes its own time

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm(_settings().header_timeout_s)  # the next request's headers

    def connection_lost(self, exc: Exception | None) -> None:
        self._arm(None)
        super().connection_lost(exc)
