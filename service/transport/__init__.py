"""The outside world's formats and links: Zenoh bus and payload codec, MAVLink bridge and
converter, tlog/DataFlash reading, MCAP logs."""
