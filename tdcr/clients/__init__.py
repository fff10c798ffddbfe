"""Clients of a running service: the planners' client (:mod:`tdcr.clients.client`) and the bounded
load test (:mod:`tdcr.clients.loadtest`)."""

from tdcr.clients.client import AsyncClient, Client, predict_request

__all__ = ["AsyncClient", "Client", "predict_request"]
