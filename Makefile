# Two commands do everything on a fresh machine:  make demo   and   make test
# Each sets up on first use what it needs (Debian's libusb for open3d, a virtual environment,
# torch 2.13.0 CPU first so nothing pulls a CUDA build, then ffrecon with its test and export extras,
# then Depth Anything 3 without its declared dependencies).

PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.ffrecon-installed
DEMO_OUT ?= demo_out

.PHONY: demo test test-fast lint setup clients colmap-cli clean bench

setup: $(STAMP)

$(STAMP): pyproject.toml
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so'; then \
		echo "installing Debian's libusb-1.0-0 (open3d needs it)"; \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq libusb-1.0-0; \
	fi
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[test]'
	$(PY) -m pip install -q --no-deps depth-anything-3==0.1.1  # its declared deps pin numpy<2; the ones it needs come with [export]
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/ffrecon demo -o $(DEMO_OUT) --overwrite

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

test: lint clients
	$(PY) -m pytest

# The clients ffrecon's outputs are tested in: Debian's chromium (headless) and the npm packages pinned in
# clients/package-lock.json (splat-transform, Spark, three, puppeteer-core; no browser download) for the web
# (tests/formats/test_web_clients.py); nerfstudio's data parsers (pinned, into clients/python, without
# the training stack they do not import) and Debian's COLMAP 3.8 command line for the desktop
# (tests/formats/test_desktop_clients.py). Optional: whatever cannot be installed, the tests that need it
# are skipped with the reason.
CLIENTS_STAMP := clients/node_modules/.ffrecon-installed
NERFSTUDIO_STAMP := clients/python/.ffrecon-installed
NERFSTUDIO_PINS := nerfstudio==1.1.5 jaxtyping==0.3.11 tensorboard==2.21.0 absl-py==2.5.1 appdirs==1.4.4 rawpy==0.28.0

clients: $(CLIENTS_STAMP) $(NERFSTUDIO_STAMP) colmap-cli

$(NERFSTUDIO_STAMP): $(STAMP) Makefile
	rm -rf clients/python
	$(PY) -m pip install -q --no-deps --target clients/python $(NERFSTUDIO_PINS) && touch $@ \
		|| echo "WARNING: could not install nerfstudio's parsers; the nerfstudio tests will be skipped"

colmap-cli:
	@if ! command -v colmap >/dev/null 2>&1; then \
		echo "installing Debian's colmap (its command line reads ffrecon's sparse/0 in the client tests)"; \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		{ $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq colmap >/dev/null; } \
			|| echo "WARNING: could not install colmap; the COLMAP command-line tests will be skipped"; \
	fi

$(CLIENTS_STAMP): clients/package.json clients/package-lock.json
	@if ! command -v chromium >/dev/null 2>&1; then \
		echo "installing Debian's chromium (headless, for the web-client tests)"; \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		{ $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq chromium >/dev/null; } \
			|| echo "WARNING: could not install chromium; the headless-browser tests will be skipped"; \
	fi
	@if ! command -v npm >/dev/null 2>&1; then \
		echo "installing Debian's nodejs and npm (for the web-client tests)"; \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		{ $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq nodejs npm >/dev/null; } \
			|| echo "WARNING: could not install npm"; \
	fi
	@if command -v npm >/dev/null 2>&1; then \
		npm ci --prefix clients --no-audit --no-fund --ignore-scripts --loglevel=error && touch $@ \
			|| echo "WARNING: npm ci failed in clients/; the web-client tests will be skipped"; \
	else \
		echo "WARNING: npm not found (apt-get install npm); the web-client tests will be skipped"; \
	fi

test-fast: $(STAMP)
	$(PY) -m pytest -m "not slow"

bench: $(STAMP)
	$(PY) tools/bench_refine.py
	$(PY) tools/bench_splat.py

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache clients/node_modules clients/python
