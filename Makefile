# mavloc: two commands do everything on a fresh Debian machine that has rustup.
#   make demo   the end-to-end demonstration
#   make test   every check CI runs (fmt, clippy, all tests)
#   make check-long   the full-size runs the suite leaves out (minutes each)
# Both first run `make deps`, which installs only what is missing.

APT_PACKAGES := libopencv-dev clang libclang-dev fonts-dejavu-core
PYTHON ?= python3
PYMAVLINK_VERSION := 2.4.50
CARGO ?= cargo
SUDO := $(shell [ "$$(id -u)" -eq 0 ] || echo sudo)

.PHONY: deps demo test check-long build release install uninstall clean

deps:
	@command -v $(CARGO) >/dev/null || { echo "make deps: cargo not found; install Rust with rustup first" >&2; exit 1; }
	@missing=""; \
	for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "make deps: installing Debian packages:$$missing"; \
	  $(SUDO) apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $$missing >/dev/null || exit 1; \
	fi
	@$(PYTHON) -c "import pymavlink" 2>/dev/null || { \
	  echo "make deps: installing pymavlink $(PYMAVLINK_VERSION) from PyPI"; \
	  $(PYTHON) -m pip install --quiet "pymavlink==$(PYMAVLINK_VERSION)"; }
	@$(CARGO) fmt --version >/dev/null 2>&1 && $(CARGO) clippy --version >/dev/null 2>&1 \
	  && { rustup which clippy-driver >/dev/null 2>&1 || command -v clippy-driver >/dev/null; } || { \
	  echo "make deps: rustfmt and clippy are needed: rustup component add rustfmt clippy" >&2; exit 1; }

demo: deps
	$(CARGO) run --release --quiet -- demo

# Clippy lints the workspace while the tests build, by the mechanism `cargo clippy`
# itself uses (clippy-driver as RUSTC_WORKSPACE_WRAPPER, lint flags in CLIPPY_ARGS):
# dependencies (OpenCV's bindings above all) compile once instead of once for
# `cargo clippy` and again for `cargo test`. Both cargo calls carry the same wrapper,
# so the second reuses the first's build.
CLIPPY_DRIVER = $(shell rustup which clippy-driver 2>/dev/null || command -v clippy-driver)
LINTED = RUSTC_WORKSPACE_WRAPPER=$(CLIPPY_DRIVER) CLIPPY_ARGS=-Dwarnings
test: deps
	$(CARGO) fmt --all -- --check
	$(LINTED) $(CARGO) test --workspace --all-targets --no-run
	$(LINTED) $(CARGO) test --workspace

# Full-size runs: the demo's own test and the long end-to-end flights (ignored in
# `make test`, which must stay fast), then the demo itself.
check-long: deps
	$(LINTED) $(CARGO) test --workspace -- --ignored
	$(CARGO) run --release --quiet -- demo

build: deps
	$(CARGO) build --workspace

release: deps
	$(CARGO) build --release

# Installs the binary, the systemd unit and the default configuration (kept if present).
PREFIX ?= /usr/local
install: release
	install -D -m 0755 target/release/mavloc $(DESTDIR)$(PREFIX)/bin/mavloc
	install -D -m 0644 systemd/mavloc.service $(DESTDIR)/etc/systemd/system/mavloc.service
	[ -e $(DESTDIR)/etc/mavloc/mavloc.toml ] || install -D -m 0644 config/mavloc.toml $(DESTDIR)/etc/mavloc/mavloc.toml

uninstall:
	rm -f $(DESTDIR)$(PREFIX)/bin/mavloc $(DESTDIR)/etc/systemd/system/mavloc.service

clean:
	$(CARGO) clean
