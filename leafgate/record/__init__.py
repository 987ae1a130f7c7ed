"""File formats and their writers and readers, shared by the daemon, the simulator and replay.

- :mod:`~leafgate.record.recorder` — CAN logs (python-can formats) and the session recorder
- :mod:`~leafgate.record.session` — the MCAP session format (write and read)
- :mod:`~leafgate.record.logs` — reading CAN logs of any python-can format
"""
