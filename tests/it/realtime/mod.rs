//! Tests of the real binary that mostly wait on the wall clock: live flights against the
//! simulated vehicle (`closed_loop`), the daemon over its links from pymavlink
//! (`daemon_e2e`), its systemd protocol (`systemd`). Their seconds are timeouts, expiries
//! and real-time flights, not CPU: `make test` runs this module in a test process of its
//! own beside the rest (the Makefile's `test`), so they wait while the others compute
//! instead of taking the others' test threads. The module's name must stay unique among
//! test names, since the rest is run with `--skip realtime::`
//! (`layers::no_other_test_path_holds_the_realtime_filter`).

mod closed_loop;
mod daemon_e2e;
mod systemd;
