PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# kernels compiled ahead of time (adaptnav/kernels.py), rebuilt when their sources change
KERNELS := $(VENV)/.kernels
KERNEL_SOURCES := fusion/strapdown.py fusion/kalman.py calibration/_kernels.py sonar/_kernels.py adaptnav/kernels.py

.PHONY: demo test test-sitl bench golden browser clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --upgrade pip >/dev/null
	$(BIN)/pip install -e '.[test,bench]'
	touch $(STAMP)

$(KERNELS): $(STAMP) $(KERNEL_SOURCES)
	$(BIN)/adaptnav warmup  # compiled once here, not before the first solution
	touch $(KERNELS)

demo: $(STAMP) $(KERNELS)
	$(BIN)/adaptnav demo

# Debian's chromium: tests/service/test_report.py renders replay reports in it (and skips,
# saying why, where it cannot be installed)
browser:
	@command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 || \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) || \
	  echo "make browser: chromium could not be installed; the report test will skip"

test: $(STAMP) $(KERNELS) browser
	$(BIN)/python -m pytest -q -n 2 --dist loadgroup tests

# regenerate the golden replay references (tests/golden/) after a change of behaviour made
# on purpose; the commit says why the numbers moved
golden: $(STAMP) $(KERNELS)
	$(BIN)/python -m tests.golden.golden

# the daemon against a real ArduSub (../shared/sitl) on loopback, its MAVLink link cut for
# 10 s mid-lane, and the same autopilot's DataFlash log of a drive replayed: paces on the
# wall clock (~12 min), so not part of `make test`; skips when the binary is absent. Figures
# and the recordings go to out/sitl (report.json, session.tlog, dropout.json; bin/report.json,
# bin/ardusub.BIN, bin/session.tlog).
test-sitl: $(STAMP)
	ADAPTNAV_SITL_OUT=out/sitl $(BIN)/python -m pytest -q -s -n 0 -m sitl tests/sitl

bench: $(STAMP) $(KERNELS)
	$(BIN)/adaptnav bench fusion
	$(BIN)/adaptnav bench calibration
	$(BIN)/adaptnav bench sonar

clean:
	rm -rf $(VENV) out *.egg-info
