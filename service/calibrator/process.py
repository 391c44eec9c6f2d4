"""The former home of the calibrator supervisor, split into focused modules; this import
path stays for code written against it (it re-exports, nothing else — new code imports
from the modules below):

- :mod:`adaptnav.service.calibrator.batching` — compaction, packing, data time;
- :mod:`adaptnav.service.calibrator.lagged` — replay's release rule and backends;
- :mod:`adaptnav.service.calibrator.live` — the daemon's supervised child;
- :mod:`adaptnav.service.calibrator.node` — the calibrator as a bus node, and the daemon's side of it;
- :mod:`adaptnav.service.transport.release` — the release codec;
- :mod:`adaptnav.service.compose` — building calibrators from the config.
"""
from adaptnav.service.calibrator.batching import compact_imu, data_time, pack_batch, unpack_batch  # noqa: F401
from adaptnav.service.calibrator.lagged import (CHILD_THREAD_ENV, InlineBackend, LaggedCalibrator,  # noqa: F401
                                                ProcessBackend, _cpu_s, limit_child_threads, prestart)
from adaptnav.service.calibrator.live import CalibratorProcess  # noqa: F401
from adaptnav.service.calibrator.node import RemoteCalibrator, run_node  # noqa: F401
from adaptnav.service.compose import make_calibrator, make_lagged_calibrator  # noqa: F401
from adaptnav.service.transport.release import release_from_dict, release_to_dict  # noqa: F401
