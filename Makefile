# mavloc: two commands do everything on a fresh Debian machine that has rustup.
#   make demo   the end-to-end demonstration
#   make test   every check CI runs (fmt, clippy, all tests)
#   make check-long   the full-size runs the suite leaves out (minutes each)
# Both first run `make deps`, which installs only what is missing.
# `make install` needs only a Rust toolchain and the build packages (`make build-deps`).

BUILD_PACKAGES := libopencv-dev clang libclang-dev
# dpkg-dev: `make deb` (dpkg-shlibdeps works out the package's library dependencies).
APT_PACKAGES := $(BUILD_PACKAGES) fonts-dejavu-core python3-venv dpkg-dev
# The interpreter the test tools' virtual environment is made from. Debian's own
# (`/usr/bin/python3`) is "externally managed" and refuses `pip install`, so the tools go
# into a project venv, never into the system interpreter.
PYTHON ?= python3
VENV := .venv
PYMAVLINK_VERSION := 2.4.50
# The tests run pymavlink from the venv (tests/it reads MAVLOC_PYTHON).
export MAVLOC_PYTHON := $(abspath $(VENV))/bin/python
CARGO ?= cargo
SUDO := $(shell [ "$$(id -u)" -eq 0 ] || echo sudo)

.PHONY: deps build-deps demo test check-long bench sitl build release install install-files uninstall deb deb-files clean

# Debian packages, installed only when missing.
define apt_install
	@missing=""; \
	for p in $(1); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "make: installing Debian packages:$$missing"; \
	  $(SUDO) apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $$missing >/dev/null || exit 1; \
	fi
endef

build-deps:
	@command -v $(CARGO) >/dev/null || { echo "make: cargo not found; install Rust with rustup first (under sudo: sudo env PATH=\"$$PATH\" make ...)" >&2; exit 1; }
	$(call apt_install,$(BUILD_PACKAGES))

deps: build-deps
	$(call apt_install,$(APT_PACKAGES))
	@$(VENV)/bin/python -c "import pymavlink" 2>/dev/null || { \
	  echo "make deps: creating $(VENV) from $(PYTHON) with pymavlink $(PYMAVLINK_VERSION)"; \
	  rm -rf $(VENV) && $(PYTHON) -m venv $(VENV) && \
	  $(VENV)/bin/pip install --quiet --disable-pip-version-check "pymavlink==$(PYMAVLINK_VERSION)"; }
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
# Two test processes at once: `realtime::` (tests/it/realtime: live flights and the
# daemon's links, which mostly wait on the wall clock) on REALTIME_THREADS threads, and
# everything else on TEST_THREADS, so the waiting tests hold none of the computing ones'
# threads (one process on four threads left two cores half idle while four waiting tests
# ran side by side; docs/history-suite.md, session 42). Cargo builds nothing here (the
# line before built it all), so the two runs do not wait for each other's lock. The
# rest's output streams; the realtime run's is kept and shown after it. Each runs in a
# process group of its own (setsid) while the shell waits for both: an interrupted
# `make test` (Ctrl-C, a TERM or a closed terminal) stops both groups and exits with
# 128 + the signal. (The e2e scripts each run in a session of their own and end with
# their daemons within their own time bound: nothing was left 30 s after an interrupt.)
TEST_THREADS ?= 3
REALTIME_THREADS ?= 4
REALTIME_LOG := $(or $(CARGO_TARGET_DIR),target)/realtime-tests.log
test: deps
	$(CARGO) fmt --all -- --check
	$(LINTED) $(CARGO) test --workspace --all-targets --no-run
	@echo "make test: the realtime:: tests run beside the rest; their output follows (also in $(REALTIME_LOG))"; \
	rt=; rest=; \
	stop() { for g in $$rt $$rest; do kill -TERM -$$g 2>/dev/null; done; echo "make test: stopped" >&2; exit $$1; }; \
	trap 'stop 130' INT; trap 'stop 143' TERM; trap 'stop 129' HUP; \
	mkdir -p "$$(dirname $(REALTIME_LOG))"; \
	$(LINTED) setsid -w $(CARGO) test --test it -- --test-threads $(REALTIME_THREADS) realtime:: > $(REALTIME_LOG) 2>&1 & rt=$$!; \
	$(LINTED) setsid -w $(CARGO) test --workspace -- --test-threads $(TEST_THREADS) --skip realtime:: & rest=$$!; \
	wait $$rest; rest_status=$$?; \
	wait $$rt; realtime=$$?; cat $(REALTIME_LOG); \
	if [ $$rest_status -ne 0 ] || [ $$realtime -ne 0 ]; then \
	  echo "make test: failed (exit $$rest_status for the rest, $$realtime for realtime::)" >&2; exit 1; fi

# Full-size runs: the demo's own test and the long end-to-end flights (ignored in
# `make test`, which must stay fast), then the demo itself DEMO_RUNS times in a row (a
# first command that fails by chance is worse than a slow one): each run's result and
# worst landmark, and how many passed.
DEMO_RUNS ?= 10
check-long: deps
	$(LINTED) $(CARGO) test --workspace -- --ignored
	$(CARGO) build --release --quiet
	@mkdir -p out/demo-loop; passed=0; for i in $$(seq 1 $(DEMO_RUNS)); do \
	  target/release/mavloc demo --out out/demo-loop/$$i > out/demo-loop-$$i.txt 2>&1; code=$$?; \
	  worst=$$(grep -o 'max [0-9.]*)' out/demo-loop-$$i.txt | head -1); \
	  echo "demo run $$i: exit $$code, coastline landmark $$worst"; \
	  [ $$code -eq 0 ] && passed=$$((passed + 1)); \
	done; echo "demo: $$passed of $(DEMO_RUNS) runs passed"; [ $$passed -eq $(DEMO_RUNS) ]

# Criterion benches of the hot stages (release), then one table of their medians beside
# the frames/s and accuracy of full runs made in the same invocation on rendered data
# (rendered once into target/bench-data). Benches are short (1 s warm-up, 3 s each):
# compare rows of one run, the machine is shared and noisy.
bench: deps
	$(CARGO) bench --bench indoor --bench area -- --warm-up-time 1 --measurement-time 3
	$(CARGO) build --release --quiet
	$(MAVLOC_PYTHON) tools/bench_table.py --bin target/release/mavloc --data target/bench-data

# mavloc against PX4 SITL (SIH, no Gazebo), built by you outside this project:
#   MAVLOC_PX4_DIR=/path/to/PX4-Autopilot/build/px4_sitl_default make sitl
# Results in results/sitl/<scenario>/ (report.json, PX4's .ulg, logs). Skipped without it.
# Default scenarios: indoor (GPS off) and coastline-border (mavloc points the gimbal).
# SITL_ARGS="--scenario coastline-mission": the mission's ROI items point it instead;
# "--repeat N" cold starts; "--px4-param NAME=VALUE", "--set KEY=VALUE" on top of the configs.
# A release build, as a drone runs it (the dev profile compiles mavloc at opt-level 1).
sitl: deps
	@if [ -z "$(MAVLOC_PX4_DIR)" ]; then \
	  echo "make sitl: skipped: set MAVLOC_PX4_DIR to a PX4 v1.16 SITL build folder (build/px4_sitl_default), built outside this project (README, Against PX4 SITL)"; \
	else \
	  $(CARGO) build --release && \
	  { $(MAVLOC_PYTHON) -c "import pyulog" 2>/dev/null || $(VENV)/bin/pip install --quiet --disable-pip-version-check "pyulog==1.3.0"; } && \
	  $(MAVLOC_PYTHON) tools/sitl.py --px4 "$(MAVLOC_PX4_DIR)" --mavloc target/release/mavloc --out results/sitl $(SITL_ARGS); \
	fi

build: build-deps
	$(CARGO) build --workspace

release: build-deps
	$(CARGO) build --release

# Installs the binary, the systemd unit (ExecStart pointing at $(PREFIX)) and the
# real-drone configuration. An existing configuration is never replaced, nor is a unit
# someone edited: local changes belong in /etc/systemd/system/mavloc.service.d/*.conf
# (README, "Running on a drone"). systemd is told when it is running (not in a DESTDIR).
PREFIX ?= /usr/local
UNIT := $(DESTDIR)/etc/systemd/system/mavloc.service
# The unit as last installed, to tell an edited unit from an older release's.
PRISTINE := $(DESTDIR)$(PREFIX)/share/mavloc/mavloc.service
BIN ?= target/release/mavloc
install: release
	@$(MAKE) --no-print-directory install-files

# The copying alone (tests/it/install.rs runs it on a debug binary into a DESTDIR).
install-files:
	install -D -m 0755 $(BIN) $(DESTDIR)$(PREFIX)/bin/mavloc
	@mkdir -p $(dir $(UNIT)) $(dir $(PRISTINE))
	@sed 's|/usr/local/bin/mavloc|$(PREFIX)/bin/mavloc|' systemd/mavloc.service > $(UNIT).new
	@if [ -e $(UNIT) ] && ! cmp -s $(UNIT) $(UNIT).new && ! cmp -s $(UNIT) $(PRISTINE); then \
	  echo "make install: $(UNIT) was edited, so it is kept; the new unit is $(UNIT).new (put local changes in mavloc.service.d/)"; \
	else mv $(UNIT).new $(UNIT); fi
	@sed 's|/usr/local/bin/mavloc|$(PREFIX)/bin/mavloc|' systemd/mavloc.service > $(PRISTINE)
	[ -e $(DESTDIR)/etc/mavloc/mavloc.toml ] || install -D -m 0644 config/drone.toml $(DESTDIR)/etc/mavloc/mavloc.toml
	@if [ -z "$(DESTDIR)" ] && [ -d /run/systemd/system ]; then systemctl daemon-reload; fi

uninstall:
	@if [ -z "$(DESTDIR)" ] && [ -d /run/systemd/system ]; then \
	  systemctl disable --now mavloc.service 2>/dev/null || true; fi
	rm -f $(DESTDIR)$(PREFIX)/bin/mavloc $(UNIT) $(UNIT).new $(PRISTINE)
	@if [ -z "$(DESTDIR)" ] && [ -d /run/systemd/system ]; then systemctl daemon-reload; fi
	@echo "make uninstall: kept /etc/mavloc and /var/lib/mavloc (configuration, results)"

# A Debian package: the binary (/usr/bin), the unit (/usr/lib/systemd/system, so local
# changes go in /etc/systemd/system/mavloc.service.d/), the real-drone configuration as a
# conffile (/etc/mavloc/mavloc.toml: dpkg never overwrites an edited one on upgrade), the
# demo and SITL configurations as examples, and maintainer scripts that reload systemd
# and stop/disable the service on removal. The README goes in with the docs/ folder it
# links to (notes, pictures and their licences), its link to the demo configuration
# pointing at the packaged example. Built with dpkg-deb itself, from the same files as
# `make install`: target/debian/mavloc_<version>_<arch>.deb.
DEB_DIR ?= target/debian
DEB_COMPRESS ?= xz
DEB_MAINTAINER ?= mavloc developers <mavloc@localhost>
deb: release
	$(call apt_install,dpkg-dev)
	@$(MAKE) --no-print-directory deb-files STRIP=1

# The packaging alone (tests/it/install.rs runs it on a debug binary, uncompressed).
deb-files:
	@set -e; stage=$(DEB_DIR)/stage; rm -rf $$stage; \
	version=$$(sed -n 's/^version = "\(.*\)"/\1/p' Cargo.toml | head -1); \
	arch=$$(dpkg --print-architecture); \
	install -D -m 0755 $(BIN) $$stage/usr/bin/mavloc; \
	if [ -n "$(STRIP)" ]; then strip --strip-unneeded $$stage/usr/bin/mavloc; fi; \
	mkdir -p $$stage/usr/lib/systemd/system; \
	sed 's|/usr/local/bin/mavloc|/usr/bin/mavloc|; s|`make install`|the package|' systemd/mavloc.service > $$stage/usr/lib/systemd/system/mavloc.service; \
	install -D -m 0644 config/drone.toml $$stage/etc/mavloc/mavloc.toml; \
	install -D -m 0644 config/mavloc.toml $$stage/usr/share/doc/mavloc/examples/demo.toml; \
	install -m 0644 config/sitl.toml config/sitl-indoor.toml config/photo-survey.toml $$stage/usr/share/doc/mavloc/examples/; \
	install -m 0644 packaging/deb/copyright $$stage/usr/share/doc/mavloc/; \
	sed 's|](config/mavloc.toml)|](examples/demo.toml)|g' README.md > $$stage/usr/share/doc/mavloc/README.md; \
	install -D -m 0644 -t $$stage/usr/share/doc/mavloc/docs docs/*; \
	mkdir -p $$stage/DEBIAN; \
	install -m 0755 packaging/deb/postinst packaging/deb/prerm packaging/deb/postrm $$stage/DEBIAN/; \
	echo /etc/mavloc/mavloc.toml > $$stage/DEBIAN/conffiles; \
	shl=$$(mktemp -d); mkdir $$shl/debian; printf 'Source: mavloc\n\nPackage: mavloc\nArchitecture: any\n' > $$shl/debian/control; \
	depends=$$(cd $$shl && dpkg-shlibdeps -O --warnings=0 -e $(abspath $(DEB_DIR))/stage/usr/bin/mavloc | sed 's/^shlibs:Depends=//'); \
	rm -rf $$shl; \
	size=$$(du -sk --exclude=DEBIAN $$stage | cut -f1); \
	sed -e "s|@VERSION@|$$version|" -e "s|@ARCH@|$$arch|" -e "s|@DEPENDS@|$$depends|" \
	    -e "s|@SIZE@|$$size|" -e "s|@MAINTAINER@|$(DEB_MAINTAINER)|" packaging/deb/control.in > $$stage/DEBIAN/control; \
	deb=$(DEB_DIR)/mavloc_$${version}_$${arch}.deb; \
	dpkg-deb --root-owner-group -Z$(DEB_COMPRESS) --build $$stage $$deb >/dev/null; \
	rm -rf $$stage; echo "make deb: $$deb"

clean:
	$(CARGO) clean
