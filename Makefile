# Two targets do all the set-up on a fresh clone: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test install bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/telefringe demo telefringe-demo --force

test: $(STAMP) system-packages
	$(BIN)/ruff check .
	$(BIN)/lint-imports
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --durations=15

# Debian packages the capture-driver tests need: the Aravis library (GigE Vision tests
# against its fake camera), Xvfb + xrandr + Mesa's software GL (the window projector).
# Installed only as root where apt-get exists, and only those missing (a no-op once there);
# elsewhere those tests skip and say why.
SYSTEM_PACKAGES := libaravis-0.8-0 xvfb x11-xserver-utils libgl1 libglx-mesa0 libgl1-mesa-dri
.PHONY: system-packages
system-packages:
	@if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	  missing=$$(for p in $(SYSTEM_PACKAGES); do \
	    dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "ok installed" || echo $$p; done); \
	  if [ -n "$$missing" ]; then \
	    echo "installing Debian packages for the driver tests:" $$missing; \
	    export DEBIAN_FRONTEND=noninteractive; \
	    apt-get install -y -qq --no-install-recommends $$missing >/dev/null 2>&1 \
	    || { apt-get update -qq >/dev/null 2>&1 \
	         && apt-get install -y -qq --no-install-recommends $$missing >/dev/null; } \
	    || echo "could not install" $$missing "- the tests that need them will skip"; \
	  fi; \
	fi

bench: $(STAMP)
	$(BIN)/python benchmarks/render.py
	$(BIN)/python benchmarks/decode.py
	$(BIN)/python benchmarks/reconstruct.py

clean:
	rm -rf $(VENV) build src/*.egg-info .pytest_cache .ruff_cache
