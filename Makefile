PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --upgrade pip >/dev/null
	$(BIN)/pip install -e '.[test,bench]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/adaptnav demo

test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 tests

bench: $(STAMP)
	$(BIN)/adaptnav bench fusion
	$(BIN)/adaptnav bench calibration
	$(BIN)/adaptnav bench sonar

clean:
	rm -rf $(VENV) out *.egg-info
