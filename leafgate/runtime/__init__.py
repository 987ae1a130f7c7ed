"""The imperative shell around the pure core: threads, sockets, the clock.

- :mod:`~leafgate.runtime.slots` — the latest-value slot every input is kept in
- :mod:`~leafgate.runtime.receiver` — the CAN receiver (Notifier listener) and its echo filter
- :mod:`~leafgate.runtime.node` — the gateway's Zenoh node (input slots, publishers, engage)
- :mod:`~leafgate.runtime.loop` — the fixed-rate loop around ``Gateway.step``
- :mod:`~leafgate.runtime.daemon` — the daemon's composition root (``leafgate run``)
- :mod:`~leafgate.runtime.signals` — SIGINT, SIGTERM and SIGHUP as the controlled stop
- :mod:`~leafgate.runtime.hold` — SIGTERM and SIGHUP held from the command's first line
- :mod:`~leafgate.runtime.systemd` — systemd notification
"""
