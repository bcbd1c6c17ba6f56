# Two entry points for a newcomer: `make demo` and `make test`. Both install everything first.
PYTHON ?= python3
SUDO := $(shell [ "$$(id -u)" = "0" ] || echo sudo)
SYSTEM_PACKAGES := libusb-1.0-0 libgl1 libegl1 libxrender1 libgomp1
DEMO_OUT ?= demo_out

.PHONY: setup system-packages demo test bench bench-manifest bench-scale bench-real-size bench-quality bench-rays clean

setup: .setup.stamp

system-packages:
	@missing=""; for p in $(SYSTEM_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then echo "installing system packages:$$missing"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq $$missing; fi

.setup.stamp: pyproject.toml | system-packages
	$(PYTHON) -m pip install -q -e ".[dev]"
	@touch $@

demo: setup
	$(PYTHON) -m nuplan_occ.cli demo $(DEMO_OUT)

test: setup
	$(PYTHON) -m pytest -q

bench: setup
	$(PYTHON) -m benchmarks.small bench

bench-manifest: setup
	$(PYTHON) -m benchmarks.manifest --out bench

# Real-scale yardstick: city logs of one 5 / 10 / 20 s scene, one worker; bench/report-scale.{json,md}.
bench-scale: setup
	nice -n 5 $(PYTHON) -m benchmarks.scale

# Real-size log: a 20-minute log's row counts without a box index; open and load times, peak RSS,
# before (git archive of the old revision) and after; bench/report-real-size-log.{json,md}.
bench-real-size: setup
	nice -n 5 $(PYTHON) -m benchmarks.real_size_log --work bench/real_size --out bench

# Quality matrix: 10 synthetic worlds of 20 s (tuning / held-out seeds, imperfect logs, another layout);
# bench/report-quality.{json,md}. QUALITY_ARGS e.g. --worlds city-s7 --seconds 5.
bench-quality: setup
	nice -n 5 $(PYTHON) -m benchmarks.quality_matrix $(QUALITY_ARGS)

# Ray consistency calibrated against truth: the truth-free per-frame scores against true IoU on damaged
# synthetic worlds; bench/report-ray-consistency.{json,md}.
bench-rays: setup
	nice -n 5 $(PYTHON) -m benchmarks.ray_consistency

clean:
	rm -rf $(DEMO_OUT) bench/work bench/data bench/manifest_work bench/real_size .setup.stamp
