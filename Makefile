# Two entry points on a fresh machine with Python 3.11: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
PIP := $(VENV)/bin/python -m pip install --disable-pip-version-check -q -c constraints.txt

.PHONY: demo test extension bench clean

$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)

# Stamps make the installs idempotent: they rerun only when the dependency lists change.
$(VENV)/.run-installed: pyproject.toml constraints.txt | $(VENV)/bin/python
	$(PIP) -e '.[blender,scripts]'
	touch $@

$(VENV)/.dev-installed: $(VENV)/.run-installed
	$(PIP) -e '.[blender,scripts,dev,learn]'
	touch $@

demo: $(VENV)/.run-installed
	$(VENV)/bin/python headless_scripts/demo.py --out demo_output

test: $(VENV)/.dev-installed
	$(VENV)/bin/python -m pytest

extension: $(VENV)/.run-installed
	$(VENV)/bin/python headless_scripts/build_extension.py

bench: $(VENV)/.dev-installed
	$(VENV)/bin/python headless_scripts/bench_import.py
	$(VENV)/bin/python headless_scripts/bench_alignment.py
	$(VENV)/bin/python headless_scripts/bench_heading.py
	$(VENV)/bin/python headless_scripts/bench_scan.py
	$(VENV)/bin/python headless_scripts/bench_intensity.py
	$(VENV)/bin/python headless_scripts/bench_bank.py

clean:
	rm -rf $(VENV) dist demo_output
