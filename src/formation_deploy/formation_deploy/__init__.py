"""Deployment and security: the compose generator (``formation-compose``), keys (``formation-keys``), the
secure-mode TLS profiles (:mod:`secure_transport`) and intruder detection (:mod:`publisher_watch`,
:mod:`transport_check`, :mod:`graph_watch`)."""
