"""Zenoh transport: ROS 2 CDR / JSON payload codecs, sessions from config and the operator client.

The gateway's own node (input slots, publishers, the engage queryable) is part of the shell:
:mod:`leafgate.runtime.node`.

- :mod:`~leafgate.transport.cdr` — rosbags type store with the Autoware ``.msg`` definitions
- :mod:`~leafgate.transport.payloads` — leafgate messages ⇄ ROS messages / JSON
- :mod:`~leafgate.transport.session` — :func:`open_session` from :class:`ZenohConfig`
- :mod:`~leafgate.transport.client` — engage requests, diagnostics watch, input publishers
- :mod:`~leafgate.transport.keys` — leafgate's own key expressions after the prefix
- :mod:`~leafgate.transport.ros2` — rmw_zenoh keys, attachments, liveliness tokens, RIHS01 hashes
- :mod:`~leafgate.transport.rosnode` — :class:`RosFace`: one process's ROS 2 entities per mode

Nothing is imported here, so loading the configuration does not load Zenoh.
"""
