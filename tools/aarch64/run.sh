#!/usr/bin/env bash
# Build and test rtloop on aarch64 under qemu-user emulation, on an x86-64 Debian/Ubuntu host.
#
#   sudo tools/aarch64/run.sh [ROOT_DIR]
#
# Stages (each prints its time):
#   host     install debootstrap, qemu-user-static, binfmt-support (apt-get) when missing
#   binfmt   mount binfmt_misc and register qemu-aarch64 when missing
#   root     an arm64 Debian 12 root made by debootstrap, cached in ROOT_DIR (built once)
#   install  rtloop from this checkout (copied in) into a venv in the root, with [fmu,report], mcap, pytest;
#            the C hot path (rtloop.ipc._hotpath) must build with the root's gcc and import
#   checks   architecture facts inside the root (tests/test_cpu_facts.py), and the hot path's ordered
#            instructions counted with the root's objdump
#   tests    a part of the test suite inside the root (RTLOOP_AARCH64_TESTS)
#   compare  JIWY simulated on aarch64 and on this host, signals.csv compared bit for bit
#
# Environment:
#   RTLOOP_AARCH64_ROOT    the root (default ${XDG_CACHE_HOME:-$HOME/.cache}/rtloop/aarch64-root);
#                          the first argument wins over it
#   RTLOOP_AARCH64_MIRROR  Debian mirror for debootstrap (default: the first Debian URI of this
#                          host's apt sources, else http://deb.debian.org/debian)
#   RTLOOP_AARCH64_TESTS   pytest arguments run inside (default: the tests listed below)
#   RTLOOP_AARCH64_OUT     where results go (default: a new temporary directory)
#   HOST_PYTHON            the x86-64 Python with rtloop's dependencies for the comparison
#                          (default: .venv/bin/python of this checkout, else python3)
# Needs root (debootstrap, chroot, mounts). Exit status: 0 only if every stage passed.
set -euo pipefail

# All in one function: bash reads a script as it runs it, and this one runs for many
# minutes; parsing it whole first means an edit of the file cannot change a run under way.
main() {

    repo=$(cd "$(dirname "$0")/../.." && pwd)
    root=${1:-${RTLOOP_AARCH64_ROOT:-${XDG_CACHE_HOME:-$HOME/.cache}/rtloop/aarch64-root}}
    out=${RTLOOP_AARCH64_OUT:-$(mktemp -d /tmp/rtloop-aarch64.XXXXXX)}
    # The default selection leaves out the two stress tests of test_wiring (seconds natively, far
    # longer emulated; the torn-read one proves nothing under qemu-user, see docs/raspberry-pi.md),
    # the C hot path's torn-read stress (300k reads across cores: the same reason), its lean-process
    # test (/proc shows the qemu process, with qemu's own threads and translation buffer, not the guest's),
    # and the tests that need a 1 kHz task to keep its period: an emulated Python step takes longer
    # than 1 ms, so every cycle misses from the first and they fail for that reason alone (the
    # settings probe runs 0.1 s: a cold, emulated first step on a shared CPU does not always end in it).
    needs_native_speed="run_reproduces_simulation or ports_from_the_cli_move or run_writes_summary_and_timing"
    needs_native_speed+=" or exception_in_step_reports or ctrl_c_and_sigterm or killed_task_process_is_reported"
    needs_native_speed+=" or without_rt_privileges_it_runs or rt_settings_are_really_applied"
    default_tests=(tests/test_timing.py tests/test_models.py tests/test_models_app.py tests/test_recording.py
        tests/test_wiring.py tests/test_run.py tests/test_hotpath.py
        -k "not torn_reads and not sample_queue_delivers_every_row and not c_reader_sees_no_torn_value and not task_processes_run_one_thread and not ($needs_native_speed)")
    if [ -n "${RTLOOP_AARCH64_TESTS:-}" ]; then
        read -r -a tests <<< "$RTLOOP_AARCH64_TESTS"
    else
        tests=("${default_tests[@]}")
    fi
    suite=bookworm
    # What rtloop needs on a Pi (README, docs/raspberry-pi.md), plus ca-certificates for pip.
    packages=python3-venv,python3-dev,g++,gcc,libatomic1,ca-certificates,util-linux
    venv=/opt/rtloop-venv
    guest_src=/opt/rtloop-src
    mkdir -p "$out"

    say() { printf '\n== aarch64: %s\n' "$*"; }
    fail() { printf 'aarch64: FAILED: %s\n' "$*" >&2; exit 1; }
    timings=()
    stage_start() { stage_name=$1; stage_t0=$(date +%s); say "$1"; }
    stage_end() {
        local seconds=$(( $(date +%s) - stage_t0 ))
        timings+=("$(printf '%-8s %5d s' "$stage_name" "$seconds")")
        echo "-- $stage_name took ${seconds} s"
    }

    [ "$(id -u)" = 0 ] || fail "needs root (debootstrap, chroot and mounts); run it with sudo"
    [ "$(uname -m)" = x86_64 ] || echo "note: host is $(uname -m), not x86_64; the comparison is against it"

    # One run at a time per root: a second one would unmount what the first uses.
    mkdir -p "$(dirname "$root")"
    exec 9>"$root.lock"
    flock -n 9 || fail "another run is using $root (lock $root.lock)"

    # --- host tools --------------------------------------------------------------------------
    stage_start host
    missing=()
    command -v debootstrap >/dev/null || missing+=(debootstrap)
    [ -x /usr/bin/qemu-aarch64-static ] || missing+=(qemu-user-static)
    command -v update-binfmts >/dev/null || missing+=(binfmt-support)
    if [ ${#missing[@]} -gt 0 ]; then
        echo "installing ${missing[*]}"
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -qq
        apt-get install -y -qq "${missing[@]}" >/dev/null
    fi
    stage_end

    # --- binfmt_misc -------------------------------------------------------------------------
    stage_start binfmt
    binfmt=/proc/sys/fs/binfmt_misc
    [ -e $binfmt/register ] || mount -t binfmt_misc binfmt_misc $binfmt \
        || fail "cannot mount binfmt_misc at $binfmt (in a container: run it with --privileged)"
    if [ ! -e $binfmt/qemu-aarch64 ]; then
        update-binfmts --enable qemu-aarch64 2>/dev/null || true
    fi
    if [ ! -e $binfmt/qemu-aarch64 ]; then
        # Register by hand: ELF64, little endian, e_machine 0xb7 (AArch64); F = the kernel opens
        # the interpreter now, so it works inside the chroot without a copy there.
        echo ':qemu-aarch64:M::\x7fELF\x02\x01\x01\x00\x00\x00\x00\x00\x00\x00\x00\x00\x02\x00\xb7\x00:\xff\xff\xff\xff\xff\xff\xff\x00\xff\xff\xff\xff\xff\xff\xff\xff\xfe\xff\xff\xff:/usr/bin/qemu-aarch64-static:F' \
            > $binfmt/register || fail "cannot register qemu-aarch64 with binfmt_misc"
    fi
    grep -q enabled $binfmt/qemu-aarch64 || fail "binfmt_misc has qemu-aarch64 but it is disabled"
    interpreter=$(sed -n 's/^interpreter //p' $binfmt/qemu-aarch64)
    flags=$(sed -n 's/^flags: //p' $binfmt/qemu-aarch64)
    echo "qemu-aarch64: $interpreter (flags $flags)"
    stage_end

    # --- mounts: undone on any exit ------------------------------------------------------------
    mounted=()
    unmount_all() {
        local i
        for (( i=${#mounted[@]}-1; i>=0; i-- )); do
            umount "${mounted[i]}" 2>/dev/null || umount -l "${mounted[i]}" 2>/dev/null \
                || echo "aarch64: could not unmount ${mounted[i]}" >&2
        done
        mounted=()
        # Whatever else is left under the root (debootstrap's own /proc, if it failed half-way).
        local target
        for target in $(awk -v r="$root/" 'index($2, r) == 1 { print $2 }' /proc/mounts | sort -r); do
            umount "$target" 2>/dev/null || umount -l "$target" 2>/dev/null || true
        done
    }
    trap unmount_all EXIT
    trap 'exit 130' INT TERM
    mount_in_root() {  # mount_in_root TARGET mount-args...
        local target=$root$1
        shift
        mkdir -p "$target"
        mount "$@" "$target"
        mounted+=("$target")
    }
    mount_all() {
        mount_in_root /proc -t proc proc
        mount_in_root /sys -t sysfs sysfs || mount_in_root /sys --rbind /sys
        mount_in_root /dev --bind /dev
        mount --make-private "$root/dev"
        mount_in_root /dev/pts --bind /dev/pts
        # A private /dev/shm: rtloop's segments and registries of this root stay out of the host's.
        mount_in_root /dev/shm -t tmpfs -o mode=1777,size=256m rtloop-aarch64-shm
    }
    in_root() {  # a clean environment: nothing of the host's Python or pip settings leaks in
        env -i HOME=/root PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
            LANG=C.UTF-8 PIP_CERT=/etc/ssl/certs/ca-certificates.crt PIP_DISABLE_PIP_VERSION_CHECK=1 \
            PIP_DEFAULT_TIMEOUT=120 "$@" 2>&1
    }
    run_in_root() { in_root chroot "$root" "$@"; }
    run_pytest() {  # the checkout's tests against the rtloop installed in the root's venv
        run_in_root /usr/bin/env --chdir="$guest_src" "$venv/bin/python" -m pytest -p no:cacheprovider \
            -o addopts="--strict-markers -ra --timeout=900" "$@"
    }

    # --- the arm64 root --------------------------------------------------------------------------
    stage_start root
    if [ -e "$root/.rtloop-root-ready" ]; then
        echo "cached: $root ($(cat "$root/.rtloop-root-ready"))"
    else
        if [ -z "${RTLOOP_AARCH64_MIRROR:-}" ]; then
            RTLOOP_AARCH64_MIRROR=$(grep -rhoE '(URIs:|^deb)\s+(\[[^]]*\]\s+)?https?://[^ ]*debian/?(\s|$)' \
                /etc/apt/sources.list /etc/apt/sources.list.d/ 2>/dev/null \
                | grep -oE 'https?://[^ ]+' | grep -v security | head -1 || true)
        fi
        mirror=${RTLOOP_AARCH64_MIRROR:-http://deb.debian.org/debian}
        if grep -q " $root[/ ]" /proc/mounts; then
            fail "something is still mounted under $root (an earlier run killed hard?): umount it first"
        fi
        rm -rf "$root"
        mkdir -p "$root"
        echo "debootstrap --arch=arm64 --variant=minbase $suite $root $mirror"
        debootstrap --arch=arm64 --variant=minbase --include="$packages" "$suite" "$root" "$mirror" \
            > "$out/debootstrap.log" 2>&1 || { tail -30 "$out/debootstrap.log"; fail "debootstrap (log: $out/debootstrap.log)"; }
        # Trust what this host trusts locally (an HTTPS proxy's CA, if any), so pip inside reaches
        # the index. Appended to the bundle pip reads: update-ca-certificates takes minutes emulated.
        if compgen -G "/usr/local/share/ca-certificates/*.crt" >/dev/null; then
            cat /usr/local/share/ca-certificates/*.crt >> "$root/etc/ssl/certs/ca-certificates.crt"
        fi
        cp /etc/resolv.conf "$root/etc/resolv.conf" 2>/dev/null || true
        echo "debian $suite arm64, made $(date -u +%FT%TZ) from $mirror" > "$root/.rtloop-root-ready"
    fi
    cp /etc/resolv.conf "$root/etc/resolv.conf" 2>/dev/null || true
    if [[ $flags != *F* ]]; then
        # Without F the kernel looks the interpreter up inside the chroot: put it there.
        mkdir -p "$root$(dirname "$interpreter")"
        cp -L "$interpreter" "$root$interpreter"
    fi
    file_arch=$(run_in_root /usr/bin/dpkg --print-architecture)
    [ "$file_arch" = arm64 ] || fail "the root's dpkg says $file_arch, not arm64"
    run_in_root /usr/bin/uname -m | grep -qx aarch64 || fail "uname -m inside the root is not aarch64"
    stage_end

    mount_all

    # --- rtloop from this checkout ---------------------------------------------------------------
    stage_start install
    rm -rf "$root$guest_src"
    mkdir -p "$root$guest_src"
    # The checkout's files as git sees them (tracked and new, not ignored), with local edits.
    (cd "$repo" && git ls-files -z --cached --others --exclude-standard \
        | while IFS= read -r -d '' f; do if [ -e "$f" ]; then printf '%s\0' "$f"; fi; done \
        | tar --null -T - -cf -) | tar -xf - -C "$root$guest_src"
    [ -x "$root$venv/bin/python" ] || run_in_root python3 -m venv "$venv"
    # Debian 12's venv brings setuptools 66; the build needs >= 68. Build without isolation so
    # the C extension is compiled by the root's gcc with this venv's setuptools.
    run_in_root "$venv/bin/pip" install -q 'setuptools>=68' wheel
    # [fmu] (FMPy has a pure-Python wheel) and [report], but not [ros]: cyclonedds has no aarch64
    # wheel. [ros]'s mcap packages are pure Python and every run writes run.mcap, so they go in.
    # Of [test] only the test runners: its linter is not needed here and pip is slow emulated.
    test_packages=(mcap mcap-ros2-support pytest pytest-timeout hypothesis)
    if ! run_in_root "$venv/bin/pip" install -q --no-build-isolation "$guest_src[fmu,report]" "${test_packages[@]}" \
            > "$out/pip.log"; then
        cat "$out/pip.log"
        echo "aarch64: [fmu] did not install (FMPy), trying without it" >&2
        run_in_root "$venv/bin/pip" install -q --no-build-isolation "$guest_src" "${test_packages[@]}" \
            || fail "pip install of rtloop inside the root"
    fi
    run_in_root "$venv/bin/pip" list 2>/dev/null | grep -iE '^(rtloop|numpy|fmpy|pytest) ' || true
    # setup.py builds the C hot path as optional (a failed build only warns): here it must be there.
    run_in_root /usr/bin/env --chdir=/ "$venv/bin/python" -c \
        'from rtloop.ipc import hotpath, _hotpath; assert hotpath.c_built(); print("C hot path:", _hotpath.__file__)' \
        || fail "the C hot path rtloop.ipc._hotpath did not build or import in the aarch64 root (see $out/pip.log)"
    stage_end

    # --- aarch64 facts ---------------------------------------------------------------------------
    stage_start checks
    run_pytest -v tests/test_cpu_facts.py | tee "$out/checks.txt"
    [ "${PIPESTATUS[0]}" = 0 ] || fail "architecture checks inside the aarch64 root (see above)"
    # The figures behind test_the_compiled_hot_path_orders_its_seqlocks_with_aarch64_acquire_release.
    hotpath_so=$(run_in_root /usr/bin/env --chdir=/ "$venv/bin/python" -c 'from rtloop.ipc import _hotpath; print(_hotpath.__file__)')
    run_in_root objdump -d --no-show-raw-insn "$hotpath_so" > "$out/hotpath-objdump.txt"
    ordered=$(awk -F'\t' '$2 ~ /^(ldar|ldapr|stlr)/ { n[$2]++ } $2 == "dmb" { n["dmb " $3]++ }
        END { for (k in n) printf "%s %d, ", k, n[k] }' "$out/hotpath-objdump.txt" | sed 's/, $//')
    echo "ordered instructions in $(basename "$hotpath_so"): $ordered" | tee "$out/hotpath-ordering.txt"
    stage_end

    # --- tests -----------------------------------------------------------------------------------
    stage_start tests
    run_pytest "${tests[@]}" | tee "$out/pytest.txt"
    [ "${PIPESTATUS[0]}" = 0 ] || fail "tests inside the aarch64 root (see above)"
    stage_end

    # --- JIWY trajectories: aarch64 vs this host -------------------------------------------------
    stage_start compare
    host_python=${HOST_PYTHON:-}
    [ -n "$host_python" ] || { [ -x "$repo/.venv/bin/python" ] && host_python=$repo/.venv/bin/python; } || host_python=python3
    mkdir -p "$root/tmp/rtloop-compare"
    run_in_root sh -c "cd $guest_src && $venv/bin/python tools/aarch64/jiwy_variants.py /tmp/rtloop-compare/aarch64" \
        || fail "JIWY simulations inside the aarch64 root"
    rm -rf "$out/aarch64" && cp -r "$root/tmp/rtloop-compare/aarch64" "$out/aarch64"
    # The host side with its own C hot path too, built in a copy so the checkout is left as it is.
    host_copy=$out/host-checkout
    rm -rf "$host_copy" && mkdir -p "$host_copy"
    cp -r "$repo/src" "$repo/setup.py" "$repo/pyproject.toml" "$repo/README.md" "$host_copy/"
    find "$host_copy/src" -name '*.so' -delete
    (cd "$host_copy" && "$host_python" setup.py -q build_ext --inplace > "$out/host-build.log" 2>&1) \
        || echo "note: the host's C hot path did not build (see $out/host-build.log); the host side runs in Python"
    (cd "$repo" && PYTHONPATH="$host_copy/src" "$host_python" tools/aarch64/jiwy_variants.py "$out/$(uname -m)") \
        || fail "JIWY simulations on the host ($host_python)"
    python3 "$repo/tools/aarch64/compare_signals.py" "$out/$(uname -m)" "$out/aarch64" | tee "$out/compare.txt"
    compare_status=${PIPESTATUS[0]}
    stage_end

    say "summary (results in $out)"
    printf '  %s\n' "${timings[@]}"
    grep -E '(passed|failed)' "$out/checks.txt" | tail -1 | sed 's/^/  checks: /'
    sed 's/^/  /' "$out/hotpath-ordering.txt"
    grep -E '(passed|failed)' "$out/pytest.txt" | tail -1 | sed 's/^/  tests:  /'
    grep -E '^(same|DIFFER)' "$out/compare.txt" | sed 's/^/  /'
    [ "$compare_status" = 0 ] || fail "aarch64 and $(uname -m) trajectories differ (see $out/compare.txt)"
    echo "aarch64: all stages passed"
}

main "$@"
