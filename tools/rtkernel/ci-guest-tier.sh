#!/usr/bin/env bash
# CI's guest tier (.ci/run runs it after the host suite; runnable by hand from a checkout with
# its .venv): a selection of the tests on Debian's PREEMPT_RT kernel with real device drivers,
# in QEMU (tools/rtkernel-vm.sh, docs/rtkernel-guest.md).
#
# Emulation runs Python ~20x slower, so it runs a curated selection, in one pytest run:
#   tests/test_rtkernel_guest.py   the guest's own checks: PREEMPT_RT, SCHED_FIFO + mlockall, each
#                                  device through its driver, the JIWY demo (report, run == simulate)
#   tests/test_run.py::test_rt_settings_are_really_applied_in_the_task_process
#                                  rtloop's task processes really get SCHED_RR, priority, CPU, mlockall
#   tests/test_io_*.py             the device drivers' tests (they skip outside the guest)
# (test_run.py's other real-time tests are scaled for the guest and pass there, but each starts
# processes that take tens of seconds under emulation: they run on the host, and in the guest by
# hand: tools/rtkernel-vm.sh .venv/bin/python -m pytest -m "rt or rtkernel" tests/test_run.py.)
# Serially (-p no:xdist: pyproject.toml's addopts run the host suite in 3 processes; here one emulated
# machine runs ~20x slower, and the tests' slowdown scaling assumes it runs one test at a time).
# Prints the pytest counts and the wall time.
#
# Exit status: pytest's. A guest that cannot be prepared or booted on this machine prints
# "guest tier skipped: REASON" and exits 0 (the tier is not counted as passed); a failing
# test, a guest that panics, or one that runs past RTLOOP_RTKERNEL_TIMEOUT_S fails.
set -uo pipefail
cd "$(dirname "$0")/../.."
selection=(tests/test_rtkernel_guest.py tests/test_run.py::test_rt_settings_are_really_applied_in_the_task_process
           tests/test_io_*.py)
# The scope pin's whole-run test runs here through the compiled hot path, in both modes; its
# pure-Python variants (the same edges through the Python twin, which test_io_gpio.py checks in
# the guest as well) run in the whole selection by hand: each costs the tier 3-4 minutes under
# emulation, and CI as a whole must stay under 40 minutes.
scope_test="tests/test_io_scope_estop.py::test_the_scope_pin_changes_exactly_as_often_as_the_cycles_say"
by_hand=("$scope_test[toggle-python]" "$scope_test[step-python]")
# The CANopen drive's ways out (Ctrl-C, a drive fault, SIGKILL of the task) against its emulated node
# on vcan0: a run each, minutes under emulation; the example's run against the node is in the tier.
by_hand+=(tests/test_io_canopen.py::test_every_way_out_leaves_the_drive_quick_stopped_then_disabled)
for test in "${by_hand[@]}"; do
    echo "guest tier: by hand only (the reason above): $test"
done
log=$(mktemp)
trap 'rm -f "$log"' EXIT
started_s=$(date +%s)
RTLOOP_RTKERNEL_TIMEOUT_S=${RTLOOP_RTKERNEL_TIMEOUT_S:-3300} tools/rtkernel-vm.sh \
    .venv/bin/python -m pytest -p no:cacheprovider -p no:xdist --timeout=900 "${selection[@]}" \
    "${by_hand[@]/#/--deselect=}" 2>&1 | tee "$log"
status=${PIPESTATUS[0]}
wall_s=$(($(date +%s) - started_s))
if [ "$status" -eq 125 ]; then
    echo "guest tier skipped: $(grep '^rtkernel-vm: ' "$log" | tail -1 | sed 's/^rtkernel-vm: //')"
    exit 0
fi
counts=$(grep -E "^=+ .* in [0-9.]+s" "$log" | tail -1 | sed 's/=//g; s/^ *//; s/ *$//')
echo "guest tier: ${counts:-no pytest summary} (${#by_hand[@]} by hand only, above); wall time ${wall_s} s, boot included; exit status $status"
exit "$status"
