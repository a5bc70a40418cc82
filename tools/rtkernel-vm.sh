#!/usr/bin/env bash
# Run a command on a real PREEMPT_RT kernel with real device drivers: Debian's -rt kernel in QEMU.
#
#   tools/rtkernel-vm.sh COMMAND [ARG...]        e.g. tools/rtkernel-vm.sh python -m pytest -m rtkernel
#
# Boots Debian's linux-image-rt kernel (amd64) in QEMU with this host's /usr and /etc read-only
# (a tmpfs overlay makes them writable inside) and this project directory shared read-write at
# the same path; loads the test devices (vcan, an emulated CAN pair, i2c-stub, uinput, gpio-sim,
# a loopback SPI controller with spidev, a UART <-> USB serial loop), reports each as present or
# missing, writes the device map to /run/rtloop-guest/devices.json, then runs COMMAND as root in
# the project directory (the project's .venv/bin first on PATH). Output streams as it runs
# (stdout and stderr both arrive on stdout: they share the guest's console). The exit status is
# COMMAND's; 124 if the guest ran past its time limit (it is killed), 123 if the guest stopped
# while COMMAND ran (a kernel panic), 125 if the guest could not be prepared or did not boot to
# COMMAND, 2 for bad usage.
#
# The first run installs what is missing from the Debian registry (qemu-system-x86, kmod,
# iproute2, gcc-12, make; root or sudo needed for that) and downloads the kernel, its headers
# and its source into the cache (.rtloop-cache/rtkernel/, ignored by git); later runs work
# offline. See docs/rtkernel-guest.md.
#
# Environment:
#   RTLOOP_RTKERNEL_TIMEOUT_S  kill the guest after this many seconds (default 7200: the whole
#                              "rt or rtkernel" selection takes about an hour on a 2-core machine)
#   RTLOOP_RTKERNEL_CACHE      the cache folder (default: PROJECT/.rtloop-cache/rtkernel)
#   RTLOOP_RTKERNEL_PACKAGE    the kernel meta package (default linux-image-rt-amd64)
#   RTLOOP_RTKERNEL_UPDATE=1   ask the registry again for the newest kernel of that package
#   RTLOOP_RTKERNEL_CPUS       guest CPUs (default: 2, at most this host's count)
#   RTLOOP_RTKERNEL_MEM        guest memory (default 2G)
#   RTLOOP_RTKERNEL_SHARE      more host folders to share read-only at the same path (colon-separated)
#   RTLOOP_RTKERNEL_VERBOSE=1  show the kernel's boot messages
#   RTLOOP_RTKERNEL_QEMU_ARGS  more QEMU arguments, split at spaces, to look into a guest that hangs
#                              (e.g. '-monitor unix:/tmp/guest.mon,server,nowait', then
#                              'info registers -a' there: each CPU's RIP, against the kernel's System.map)
#   RTLOOP_TEST_SLOWDOWN       the factor tests stretch real-time periods and durations by in the
#                              guest (default 20 under emulation, 1 under KVM)
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
project=$(cd "$here/.." && pwd)
guest_files="$here/rtkernel"

say() { printf 'rtkernel-vm: %s\n' "$*" >&2; }
fail() { say "$*"; exit 125; }

if [ $# -eq 0 ] || [ "$1" = "-h" ] || [ "$1" = "--help" ]; then
    sed -n '2,/^set -euo/p' "${BASH_SOURCE[0]}" | sed '$d; s/^# \{0,1\}//' >&2
    exit 2
fi
if [ "$(uname -m)" != x86_64 ]; then
    say "this tool boots the amd64 kernel and needs an x86-64 host (this is $(uname -m))"
    exit 125
fi
timeout_s=${RTLOOP_RTKERNEL_TIMEOUT_S:-7200}
case "$timeout_s" in
    '' | *[!0-9]* | 0) say "RTLOOP_RTKERNEL_TIMEOUT_S must be a positive whole number of seconds, not '$timeout_s'"; exit 2 ;;
esac
cache=${RTLOOP_RTKERNEL_CACHE:-$project/.rtloop-cache/rtkernel}
meta_package=${RTLOOP_RTKERNEL_PACKAGE:-linux-image-rt-amd64}
started_s=$(date +%s.%N)
elapsed() { awk -v a="$started_s" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }'; }

as_root() {
    if [ "$(id -u)" -eq 0 ]; then "$@"
    elif command -v sudo >/dev/null 2>&1; then sudo "$@"
    else fail "need root (or sudo) to run: $*"
    fi
}

# --- host programs ------------------------------------------------------------------------------
ensure_host_programs() {
    local wanted=(qemu-system-x86_64:qemu-system-x86 depmod:kmod modprobe:kmod ip:iproute2
                  gcc-12:gcc-12 make:make dpkg-deb:dpkg xz:xz-utils flock:util-linux)
    local missing=() pair
    for pair in "${wanted[@]}"; do
        # depmod, modprobe and ip live in sbin, which a user's PATH may not have
        PATH="$PATH:/usr/sbin:/sbin" command -v "${pair%%:*}" >/dev/null 2>&1 || missing+=("${pair#*:}")
    done
    [ ${#missing[@]} -eq 0 ] && return 0
    say "installing from the Debian registry: ${missing[*]}"
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
        -o DPkg::Lock::Timeout=300 "${missing[@]}" >/dev/null ||
        fail "could not install ${missing[*]} with apt-get"
}

# --- the kernel, its headers and source, busybox: downloaded and extracted into the cache -------
apt_download() {  # PACKAGE[=VERSION]... into a fresh $cache/debs
    rm -rf "$cache/debs" && mkdir -p "$cache/debs"
    (cd "$cache/debs" && apt-get download -q -o APT::Sandbox::User="$(id -un)" "$@" >/dev/null) ||
        fail "apt-get download $* failed (no network, or the package lists are missing: apt-get update)"
}

resolve_kernel() {  # sets kver (e.g. 6.1.0-56-rt-amd64) and kpkg_version (e.g. 6.1.192-2)
    if [ -s "$cache/kernel" ] && [ "${RTLOOP_RTKERNEL_UPDATE:-0}" != 1 ]; then
        read -r kver kpkg_version < "$cache/kernel"
        return 0
    fi
    command -v apt-cache >/dev/null || fail "no apt-cache here: this tool needs a Debian or Ubuntu host"
    if ! apt-cache show "$meta_package" >/dev/null 2>&1; then
        say "the package lists do not know $meta_package: apt-get update"
        as_root apt-get update -qq >/dev/null || fail "apt-get update failed"
    fi
    local image
    image=$(apt-cache depends "$meta_package" 2>/dev/null | awk '/Depends: linux-image-/ { print $2; exit }')
    [ -n "$image" ] || fail "apt-cache depends $meta_package names no linux-image package"
    kver=${image#linux-image-}
    kpkg_version=$(apt-cache show "$image-unsigned" 2>/dev/null | awk '/^Version:/ { print $2; exit }')
    [ -n "$kpkg_version" ] || fail "the registry has no $image-unsigned"
    mkdir -p "$cache"
    echo "$kver $kpkg_version" > "$cache/kernel"
}

prepare_kernel() {  # $kroot: vmlinuz, modules, headers, kbuild of $kver
    kroot="$cache/$kver/root"
    [ -e "$cache/$kver/root.done" ] && return 0
    local common kbuild
    # linux-headers-6.1.0-56-rt-amd64 builds on linux-headers-6.1.0-56-common-rt and linux-kbuild-6.1
    common=$(apt-cache depends "linux-headers-$kver" | awk '/Depends: linux-headers-/ { print $2; exit }')
    kbuild=$(apt-cache depends "linux-headers-$kver" | awk '/Depends: linux-kbuild-/ { print $2; exit }')
    [ -n "$common" ] && [ -n "$kbuild" ] || fail "apt-cache depends linux-headers-$kver names no common headers or kbuild"
    # kbuild is asked for as ">= the kernel's version" and the archive keeps only its newest upload
    # (seen: image 6.1.192-2 beside kbuild 6.1.192-3 only): take the registry's candidate if it is new enough.
    local kbuild_version
    kbuild_version=$(apt-cache policy "$kbuild" | awk '/Candidate:/ { print $2; exit }')
    dpkg --compare-versions "${kbuild_version:-0}" ge "$kpkg_version" ||
        fail "the registry's $kbuild is ${kbuild_version:-missing}, older than the kernel's $kpkg_version"
    say "downloading $kver ($kpkg_version): image, headers, kbuild ($kbuild_version)"
    apt_download "linux-image-$kver-unsigned=$kpkg_version" "linux-headers-$kver=$kpkg_version" \
        "$common=$kpkg_version" "$kbuild=$kbuild_version"
    rm -rf "$kroot" && mkdir -p "$kroot"
    local deb
    for deb in "$cache/debs/"*.deb; do
        dpkg-deb -x "$deb" "$kroot"
    done
    rm -rf "$cache/debs"
    # The flavour's Makefile includes the common one by absolute path (/usr/src/...): point it here.
    sed -i "s|^include /usr/src/|include $kroot/usr/src/|" "$kroot/usr/src/linux-headers-$kver/Makefile"
    touch "$cache/$kver/root.done"
}

prepare_busybox() {
    [ -x "$cache/busybox/bin/busybox" ] && return 0
    say "downloading busybox-static"
    apt_download busybox-static
    rm -rf "$cache/busybox" && mkdir -p "$cache/busybox"
    dpkg-deb -x "$cache/debs/"busybox-static_*.deb "$cache/busybox"
    rm -rf "$cache/debs"
}

# --- modules Debian does not build: gpio-sim (from Debian's kernel source) and our SPI loopback --
gpio_sim_sources=(drivers/gpio/gpio-sim.c drivers/gpio/gpiolib.h kernel/irq/irq_sim.c)

build_gpio_sim() {
    local work="$cache/$kver/gpio-sim" src="$cache/$kver/source"
    [ -e "$work/gpio-sim.ko" ] && return 0
    if [ ! -e "$src/done" ]; then
        local major=${kver%%.0-*}
        say "downloading linux-source-$major ($kpkg_version) for gpio-sim; extracting ${#gpio_sim_sources[@]} files"
        apt_download "linux-source-$major=$kpkg_version"
        rm -rf "$src" && mkdir -p "$src"
        dpkg-deb --fsys-tarfile "$cache/debs/"linux-source-*.deb |
            tar -xO "./usr/src/linux-source-$major.tar.xz" |
            tar -xJ -C "$src" --strip-components=1 "${gpio_sim_sources[@]/#/linux-source-$major/}" ||
            fail "could not extract ${gpio_sim_sources[*]} from linux-source-$major"
        rm -rf "$cache/debs"   # 140 MB we no longer need
        touch "$src/done"
    fi
    rm -rf "$work" && mkdir -p "$work"
    cp "$src/drivers/gpio/gpio-sim.c" "$work/gpio-sim-main.c"
    cp "$src/drivers/gpio/gpiolib.h" "$work/gpiolib.h"
    cp "$src/kernel/irq/irq_sim.c" "$work/irq_sim.c"
    # Debian builds the interrupt simulator into no kernel, so it goes into this module. Its one
    # call of irq_to_desc() (not exported to modules) becomes generic_handle_irq_safe(), which
    # looks the descriptor up and handles the interrupt the same way.
    grep -q 'handle_simple_irq(irq_to_desc(irqnum));' "$work/irq_sim.c" ||
        fail "irq_sim.c of $kver no longer has the line this tool changes; see tools/rtkernel-vm.sh"
    sed -i 's/handle_simple_irq(irq_to_desc(irqnum));/generic_handle_irq_safe(irqnum);/' "$work/irq_sim.c"
    printf 'obj-m := gpio-sim.o\ngpio-sim-y := gpio-sim-main.o irq_sim.o\n' > "$work/Kbuild"
    build_module "$work" gpio-sim
}

build_spi_loopback() {
    local work="$cache/$kver/spi-loopback"
    if [ -e "$work/rtloop_spi_loopback.ko" ] && cmp -s "$guest_files/spi_loopback.c" "$work/rtloop_spi_loopback.c"; then
        return 0
    fi
    rm -rf "$work" && mkdir -p "$work"
    cp "$guest_files/spi_loopback.c" "$work/rtloop_spi_loopback.c"
    echo 'obj-m := rtloop_spi_loopback.o' > "$work/Kbuild"
    build_module "$work" rtloop_spi_loopback
}

build_module() {  # DIR NAME: build DIR/NAME.ko against the headers, install it into the module tree
    say "building $2.ko"
    make -s -C "$kroot/usr/src/linux-headers-$kver" M="$1" modules > "$1/build.log" 2>&1 || {
        tail -20 "$1/build.log" >&2
        fail "building $2.ko failed (log: $1/build.log)"
    }
    mkdir -p "$kroot/lib/modules/$kver/extra"
    cp "$1/$2.ko" "$kroot/lib/modules/$kver/extra/"
    rm -f "$cache/$kver/depmod.done"
}

run_depmod() {
    [ -e "$cache/$kver/depmod.done" ] && return 0
    PATH="$PATH:/usr/sbin:/sbin" depmod -b "$kroot" "$kver" || fail "depmod failed"
    touch "$cache/$kver/depmod.done"
}

# --- the initramfs: busybox, virtio + 9p + overlay modules, our /init -------------------------
build_initramfs() {
    initramfs="$cache/$kver/initramfs.cpio.gz"
    if [ -e "$initramfs" ] && [ "$initramfs" -nt "$guest_files/initramfs-init" ]; then
        return 0
    fi
    local work="$cache/$kver/initramfs" line
    rm -rf "$work" && mkdir -p "$work"/{bin,modules,proc,sys,dev,newroot,lower,ctl}
    cp "$cache/busybox/bin/busybox" "$work/bin/busybox"
    cp "$guest_files/initramfs-init" "$work/init" && chmod 755 "$work/init"
    # the modules to mount the shares, their dependencies first (modprobe knows the order)
    PATH="$PATH:/usr/sbin:/sbin" modprobe -d "$kroot" -S "$kver" --show-depends \
        -a virtio_pci 9pnet_virtio 9p overlay > "$work/depends" || fail "modprobe --show-depends failed"
    while read -r line; do
        case "$line" in
            insmod\ *) line=${line#insmod }; line=${line%% *}
                       grep -qx "$(basename "$line")" "$work/modules/order" 2>/dev/null && continue
                       cp "$line" "$work/modules/"; basename "$line" >> "$work/modules/order" ;;
        esac
    done < "$work/depends"
    (cd "$work" && find . -path ./depends -prune -o -print | "$cache/busybox/bin/busybox" cpio -o -H newc 2>/dev/null) |
        gzip -1 > "$initramfs.tmp"
    mv "$initramfs.tmp" "$initramfs"
}

prepare() {
    ensure_host_programs
    mkdir -p "$cache"
    exec 9> "$cache/lock"
    flock 9   # two runs from the same project prepare the cache one after the other
    resolve_kernel
    prepare_kernel
    prepare_busybox
    build_gpio_sim
    build_spi_loopback
    run_depmod
    build_initramfs
    flock -u 9
}

# --- run ------------------------------------------------------------------------------------------
free_udp_port() {
    local port
    for _ in $(seq 50); do
        port=$((20000 + RANDOM % 40000))
        ss -Hlun "sport = :$port" 2>/dev/null | grep -q . || { echo "$port"; return 0; }
    done
    echo $((20000 + RANDOM % 40000))
}

prepare
say "kernel $kver ready after $(elapsed) s"

if grep -qwE 'vmx|svm' /proc/cpuinfo && [ -w /dev/kvm ]; then
    accel=(-accel kvm -cpu host); accel_name=kvm
else
    # /dev/kvm may exist without hardware virtualisation (a paravirtualised host): emulate
    accel=(-accel tcg,thread=multi -cpu max); accel_name=tcg
fi
cpus=${RTLOOP_RTKERNEL_CPUS:-$(($(nproc) < 2 ? $(nproc) : 2))}
memory=${RTLOOP_RTKERNEL_MEM:-2G}

ctl=$(mktemp -d "${TMPDIR:-/tmp}/rtkernel-vm.XXXXXX")
qemu_pid=
cleanup() {
    [ -n "$qemu_pid" ] && kill "$qemu_pid" 2>/dev/null
    rm -rf "$ctl"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# the command, one NUL-terminated argument after another (no quoting to get wrong)
printf '%s\0' "$@" > "$ctl/argv"
python_prefix=
if [ -r "$project/.venv/pyvenv.cfg" ]; then
    # the venv's interpreter may live outside /usr (pyenv, a self-built Python): share it too
    home=$(sed -n 's/^home *= *//p' "$project/.venv/pyvenv.cfg")
    if [ -n "$home" ] && [ -d "$home" ]; then
        python_prefix=$(cd "$(dirname "$(readlink -f "$home/python3")")/.." && pwd)
        case "$python_prefix/" in /usr/* | "$project"/*) python_prefix= ;; esac
    fi
fi
shares=(-virtfs "local,path=/usr,mount_tag=usr,security_model=none,multidevs=remap,readonly=on"
        -virtfs "local,path=/etc,mount_tag=etc,security_model=none,multidevs=remap,readonly=on"
        -virtfs "local,path=$kroot/lib/modules/$kver,mount_tag=modules,security_model=none,readonly=on"
        -virtfs "local,path=$project,mount_tag=project,security_model=none,multidevs=remap"
        -virtfs "local,path=$ctl,mount_tag=ctl,security_model=none")
extra_shares=
index=0
IFS=: read -r -a more <<< "${RTLOOP_RTKERNEL_SHARE:-}"
for dir in ${python_prefix:+"$python_prefix"} "${more[@]}"; do
    [ -n "$dir" ] || continue
    [ -d "$dir" ] || { say "RTLOOP_RTKERNEL_SHARE: $dir is not a folder"; exit 2; }
    dir=$(cd "$dir" && pwd)
    shares+=(-virtfs "local,path=$dir,mount_tag=extra$index,security_model=none,multidevs=remap,readonly=on")
    extra_shares+="extra$index=$dir "
    index=$((index + 1))
done
{
    echo "PROJECT='$project'"
    echo "KVER='$kver'"
    echo "EXTRA_SHARES='$extra_shares'"
    echo "ACCEL='$accel_name'"
    echo "HOST_TTY='$([ -t 1 ] && echo 1 || echo 0)'"
    echo "HOST_TERM='${TERM//[^A-Za-z0-9._-]/}'"
    echo "VERBOSE='${RTLOOP_RTKERNEL_VERBOSE:-0}'"
    slowdown=${RTLOOP_TEST_SLOWDOWN:-}
    echo "SLOWDOWN='${slowdown//[^0-9.]/}'"
} > "$ctl/config"

# the serial loop: the guest's second UART and an emulated FTDI USB adapter, wired by two UDP
# sockets on this host's loopback pointing at each other
port_a=$(free_udp_port); port_b=$(free_udp_port)
devices=(-object can-bus,id=canbus0 -device kvaser_pci,canbus=canbus0 -device kvaser_pci,canbus=canbus0
         -chardev "udp,id=uart,host=127.0.0.1,port=$port_b,localport=$port_a"
         -chardev "udp,id=usbuart,host=127.0.0.1,port=$port_a,localport=$port_b"
         -device qemu-xhci,id=xhci -device usb-serial,chardev=usbuart,always-plugged=on)
loglevel=$([ "${RTLOOP_RTKERNEL_VERBOSE:-0}" = 1 ] && echo 7 || echo 1)
say "booting ($accel_name, $cpus CPUs, $memory, time limit ${timeout_s} s)"
timeout --foreground -k 10 "$timeout_s" qemu-system-x86_64 \
    -machine q35 -bios qboot.rom "${accel[@]}" -smp "$cpus" -m "$memory" \
    -nodefaults -no-user-config -nographic -no-reboot \
    -chardev stdio,id=console,signal=on -serial chardev:console -serial chardev:uart \
    -kernel "$kroot/boot/vmlinuz-$kver" -initrd "$initramfs" \
    -append "console=ttyS0 edd=off loglevel=$loglevel panic=-1 mitigations=off rdinit=/init" \
    "${shares[@]}" "${devices[@]}" ${RTLOOP_RTKERNEL_QEMU_ARGS:-} &
qemu_pid=$!
set +e
wait "$qemu_pid"
qemu_status=$?
set -e
qemu_pid=
if [ "$qemu_status" -eq 124 ] || [ "$qemu_status" -eq 137 ]; then
    say "the guest did not finish within RTLOOP_RTKERNEL_TIMEOUT_S=$timeout_s s: killed it after $(elapsed) s"
    exit 124
fi
if [ ! -s "$ctl/status" ] && [ -e "$ctl/started" ]; then
    say "the guest stopped while the command ran, without its exit status (a kernel panic? QEMU exited with $qemu_status after $(elapsed) s)"
    exit 123
fi
if [ ! -s "$ctl/status" ]; then
    say "the guest did not boot to the command (QEMU exited with $qemu_status after $(elapsed) s; boot messages: RTLOOP_RTKERNEL_VERBOSE=1)"
    exit 125
fi
status=$(cat "$ctl/status")
say "the command exited with $status; the guest ran $(elapsed) s in all"
exit "$status"
