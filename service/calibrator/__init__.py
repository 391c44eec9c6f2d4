"""The online calibrator as a process: its supervisor in the daemon, the lagged in-process
application for replay, and the remote calibrator node."""
