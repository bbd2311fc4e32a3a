# Two entry points on a fresh machine with Python 3.11: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
PIP := $(VENV)/bin/python -m pip install --disable-pip-version-check -q -c constraints.txt
# mmdetection3d for the detector tests, in its own virtualenv: it needs numpy >= 2, bpy < 2.
MMDET3D_VENV := .venv-mmdet3d
MMDET3D_PIP := $(MMDET3D_VENV)/bin/python -m pip install --disable-pip-version-check -q \
	-c tests/detectors/mmdet3d-constraints.txt

.PHONY: demo test test-core test-blender-other extension bench clean

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

$(MMDET3D_VENV)/.installed: tests/detectors/mmdet3d-constraints.txt tests/detectors/mmcv_ext.py
	rm -rf $(MMDET3D_VENV)
	$(PYTHON) -m venv $(MMDET3D_VENV)
	$(MMDET3D_PIP) torch numpy mmengine mmcv-lite mmdet numba pyquaternion
	$(MMDET3D_PIP) --no-deps mmdet3d
	cp tests/detectors/mmcv_ext.py "$$($(MMDET3D_VENV)/bin/python -c 'import mmcv, os; print(os.path.dirname(mmcv.__file__))')/_ext.py"
	touch $@

# The other Blender versions the README claims, each in its own virtualenv with the
# project's other pins: the Blender tests and the extension install test (a few minutes each).
BPY_42 := 4.2.23
BPY_50 := 5.0.1
OTHER_BPY_VENVS := .venv-bpy42 .venv-bpy50

.venv-bpy%/.dev-installed: pyproject.toml constraints.txt
	rm -rf $(@D)
	$(PYTHON) -m venv $(@D)
	grep -v '^bpy==' constraints.txt > $(@D)/constraints.txt
	echo "bpy==$(BPY_$*)" >> $(@D)/constraints.txt
	$(@D)/bin/python -m pip install --disable-pip-version-check -q -c $(@D)/constraints.txt \
		-e '.[blender,scripts,dev,learn]'
	touch $@

test-blender-other: $(OTHER_BPY_VENVS:%=%/.dev-installed)
	for venv in $(OTHER_BPY_VENVS); do \
		$$venv/bin/python -m pytest -q tests/test_blender_*.py tests/test_extension.py || exit 1; done

test: $(VENV)/.dev-installed $(MMDET3D_VENV)/.installed test-blender-other
	$(VENV)/bin/python -m pytest

test-core: $(VENV)/.dev-installed
	$(VENV)/bin/python -m pytest -m "not blender and not slow"

extension: $(VENV)/.run-installed
	$(VENV)/bin/python headless_scripts/build_extension.py

bench: $(VENV)/.dev-installed
	$(VENV)/bin/python headless_scripts/bench_import.py
	$(VENV)/bin/python headless_scripts/bench_view_color.py
	$(VENV)/bin/python headless_scripts/bench_reconstruct.py
	$(VENV)/bin/python headless_scripts/bench_alignment.py
	$(VENV)/bin/python headless_scripts/bench_heading.py
	$(VENV)/bin/python headless_scripts/bench_scan.py
	$(VENV)/bin/python headless_scripts/bench_gaussian_scan.py
	$(VENV)/bin/python headless_scripts/bench_intensity.py
	$(VENV)/bin/python headless_scripts/bench_bank.py
	$(VENV)/bin/python headless_scripts/bench_cluster.py
	$(VENV)/bin/python headless_scripts/bench_fidelity.py
	$(VENV)/bin/python headless_scripts/bench_quality.py
	$(VENV)/bin/python headless_scripts/bench_placement.py

clean:
	rm -rf $(VENV) $(MMDET3D_VENV) $(OTHER_BPY_VENVS) dist demo_output
