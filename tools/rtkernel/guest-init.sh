#!/bin/bash
# PID 1 of the test guest after the initramfs (tools/rtkernel/initramfs-init) switched to the root
# made of the host's shares. Mounts the rest, sets up the test devices and reports each as
# present or missing with the reason, writes the device map, runs the command of
# tools/rtkernel-vm.sh in the project and hands its exit status back through the control share.
# Runs the host's own bash and tools (kmod, iproute2) from the shared /usr.
set -u
export PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
export HOME=/root LANG=C.UTF-8 TERM=dumb
ctl=/run/rtloop-guest/ctl
map=/run/rtloop-guest/devices.json
# shellcheck source=/dev/null
. "$ctl/config"

power_off() {
    sync
    umount "$ctl" 2>/dev/null
    echo o > /proc/sysrq-trigger
    # wait for the power to go without running a program (/usr is going away with its share)
    read -r -t 60 _ <> "$pause"
}
say() {
    local uptime
    read -r uptime _ < /proc/uptime
    printf 'rtkernel-vm (guest) %s s: %s\n' "$uptime" "$*"
}

mkdir -p /dev/pts /dev/shm
mount -t devpts -o newinstance,ptmxmode=0666,mode=0620 devpts /dev/pts
ln -sf pts/ptmx /dev/ptmx
mount -t tmpfs -o mode=1777,nosuid,nodev shm /dev/shm   # /tmp and /var: the initramfs mounted them
ln -sf /proc/self/fd /dev/fd
ln -sf /proc/self/fd/0 /dev/stdin; ln -sf /proc/self/fd/1 /dev/stdout; ln -sf /proc/self/fd/2 /dev/stderr
[ "$VERBOSE" = 1 ] && say "stage 2 started"
hostname rtkernel-guest
ip link set lo up
# the console is a UART: a terminal on the host wants CR LF, a log file wants LF
if [ "$HOST_TTY" = 1 ]; then export TERM="${HOST_TERM:-vt100}"; else stty -F /dev/console -onlcr 2>/dev/null; fi
[ "$VERBOSE" = 1 ] || echo 1 > /proc/sys/kernel/printk   # module taint notes would cut into the output

# --- devices -----------------------------------------------------------------------------------
json_string() {  # a JSON string of $1 (reasons come from tools' messages)
    local text=${1//\\/\\\\}
    text=${text//\"/\\\"}
    text=${text//$'\n'/ }
    text=${text//$'\t'/ }
    printf '"%s"' "$text"
}
entries=()
present() {  # NAME SUMMARY JSON-FIELDS
    say "$1: present ($2)"
    entries+=("$(json_string "$1"): {\"present\": true, $3}")
}
missing() {  # NAME REASON
    say "$1: MISSING: $2"
    entries+=("$(json_string "$1"): {\"present\": false, \"reason\": $(json_string "$2")}")
}
run() {  # COMMAND...: run it; on failure leave its last message in $why
    local out
    if out=$("$@" 2>&1); then return 0; fi
    why="$* failed: $(printf '%s' "$out" | tail -1)"
    return 1
}
load() {  # MODULE [PARAM...]: modprobe it unless it is loaded (each program run costs under emulation)
    [ -d "/sys/module/${1//-/_}" ] || run modprobe "$@"
}
wait_for() {  # PATH SECONDS: wait until PATH exists (drivers bind asynchronously)
    local deadline=$((SECONDS + $2))
    while [ ! -e "$1" ] && [ $SECONDS -lt $deadline ]; do read -r -t 0.1 _ <> "$pause"; done
    [ -e "$1" ]
}
pause=/run/rtloop-guest/pause   # a fifo nobody writes: read -t on it sleeps without a process
mkfifo "$pause"

setup_vcan() {
    local why
    load vcan && run ip link add vcan0 type vcan && run ip link set vcan0 mtu 72 up ||
        { missing vcan "$why"; return; }
    present vcan "vcan0, CAN FD MTU 72" '"interface": "vcan0", "mtu": 72'
}

setup_can() {
    local why name
    load kvaser_pci || { missing can "$why"; return; }
    for name in can0 can1; do
        wait_for "/sys/class/net/$name" 5 || { missing can "no $name after loading kvaser_pci (QEMU's two kvaser_pci on one can-bus)"; return; }
        run ip link set "$name" type can bitrate 500000 && run ip link set "$name" up || { missing can "$why"; return; }
    done
    present can "can0 <-> can1, kvaser_pci (SJA1000) on one emulated bus, 500 kbit/s" \
        '"interfaces": ["can0", "can1"], "bitrate": 500000, "driver": "kvaser_pci"'
}

i2c_addresses=(0x48 0x68)
setup_i2c() {
    local why adapter bus=
    load i2c-dev && load i2c-stub "chip_addr=$(IFS=,; echo "${i2c_addresses[*]}")" ||
        { missing i2c "$why"; return; }
    for adapter in /sys/bus/i2c/devices/i2c-*; do
        [ "$(cat "$adapter/name" 2>/dev/null)" = "SMBus stub driver" ] && bus=${adapter##*/i2c-}
    done
    [ -n "$bus" ] || { missing i2c "i2c-stub loaded but no adapter named 'SMBus stub driver'"; return; }
    wait_for "/dev/i2c-$bus" 5 || { missing i2c "no /dev/i2c-$bus (i2c-dev)"; return; }
    present i2c "/dev/i2c-$bus, i2c-stub chips at ${i2c_addresses[*]}, SMBus transfers only" \
        "\"device\": \"/dev/i2c-$bus\", \"bus\": $bus, \"addresses\": [$((i2c_addresses[0])), $((i2c_addresses[1]))], \"driver\": \"i2c-stub\""
}

setup_uinput() {
    local why
    load uinput && load evdev || { missing uinput "$why"; return; }
    wait_for /dev/uinput 5 || { missing uinput "no /dev/uinput after loading uinput"; return; }
    present uinput "/dev/uinput, events on /dev/input/event*" '"device": "/dev/uinput"'
}

# gpio-sim lines: name and the direction the device tests use them in (gpio-sim itself lets a
# consumer request any line either way; inputs are driven through the simulator's `pull`).
gpio_lines=(scope:output estop:input led:output button:input enable:output fault:input
            spare0:any spare1:any spare2:any spare3:any spare4:any spare5:any)
setup_gpio() {
    local why config=/sys/kernel/config/gpio-sim/rtloop bank offset line chip device lines=()
    load gpio-sim || { missing gpio "$why"; return; }
    mountpoint -q /sys/kernel/config || run mount -t configfs configfs /sys/kernel/config ||
        { missing gpio "$why"; return; }
    bank=$config/bank0
    mkdir "$config" "$bank" || { missing gpio "could not create $bank in configfs"; return; }
    echo rtloop-sim > "$bank/label"
    echo ${#gpio_lines[@]} > "$bank/num_lines"
    mkdir $(printf "$bank/line%s " "${!gpio_lines[@]}")   # one process: each costs under emulation
    for offset in "${!gpio_lines[@]}"; do
        line=${gpio_lines[$offset]}
        echo "${line%%:*}" > "$bank/line$offset/name"
        lines+=("\"${line%%:*}\": {\"offset\": $offset, \"direction\": \"${line#*:}\"}")
    done
    echo 1 > "$config/live" || { missing gpio "gpio-sim did not go live"; return; }
    chip=$(<"$bank/chip_name")
    device=$(<"$config/dev_name")
    wait_for "/dev/$chip" 5 || { missing gpio "no /dev/$chip"; return; }
    present gpio "/dev/$chip 'rtloop-sim', ${#gpio_lines[@]} named lines: ${gpio_lines[*]}" \
        "\"device\": \"/dev/$chip\", \"label\": \"rtloop-sim\", \"sim\": \"/sys/devices/platform/$device/$chip\", \"lines\": {$(IFS=,; echo "${lines[*]}")}"
}

setup_spi() {
    local why devices=() spidev
    load rtloop_spi_loopback || { missing spi "$why"; return; }
    wait_for /sys/bus/platform/devices/rtloop-spi-loopback 5 || { missing spi "no rtloop-spi-loopback platform device"; return; }
    for spidev in /sys/bus/platform/devices/rtloop-spi-loopback/spi_master/spi*/spi*.*/spidev/spidev*; do
        [ -e "$spidev" ] || continue
        wait_for "/dev/${spidev##*/}" 5 && devices+=("\"/dev/${spidev##*/}\"")
    done
    [ ${#devices[@]} -eq 2 ] || { missing spi "rtloop_spi_loopback loaded but spidev bound ${#devices[@]} of 2 devices"; return; }
    # chip select 1 is answered by the process holding /dev/rtloop_spi_serve open, if any (looped back otherwise)
    local serve='' served='' device
    for device in "${devices[@]}"; do [[ $device == *'.1"' ]] && served=$device; done
    [ -n "$served" ] && wait_for /dev/rtloop_spi_serve 5 && serve=', "serve": "/dev/rtloop_spi_serve", "served_device": '"$served"
    present spi "$(IFS=' '; echo "${devices[*]//\"/}"), MOSI looped back to MISO (rtloop_spi_loopback)${serve:+; ${served//\"/} served by /dev/rtloop_spi_serve}" \
        "\"devices\": [$(IFS=,; echo "${devices[*]}")], \"loopback\": true, \"max_speed_hz\": 50000000, \"driver\": \"rtloop_spi_loopback\"$serve"
}

setup_serial() {
    local why
    load xhci_pci && load ftdi_sio || { missing serial "$why"; return; }
    wait_for /dev/ttyUSB0 20 || { missing serial "no /dev/ttyUSB0 (QEMU's usb-serial, ftdi_sio) after 20 s"; return; }
    [ -e /dev/ttyS1 ] || { missing serial "no /dev/ttyS1 (the second 16550 UART)"; return; }
    stty -F /dev/ttyS1 raw -echo 115200 && stty -F /dev/ttyUSB0 raw -echo 115200
    present serial "/dev/ttyS1 (16550 UART) <-> /dev/ttyUSB0 (FTDI USB serial), ptys on /dev/ptmx" \
        '"pair": ["/dev/ttyS1", "/dev/ttyUSB0"], "uart_driver": "serial8250", "usb_driver": "ftdi_sio", "pty": "/dev/ptmx"'
}

say "$(uname -r), $(uname -v | grep -o 'PREEMPT_RT' || echo 'no PREEMPT_RT'), realtime=$(cat /sys/kernel/realtime 2>/dev/null || echo absent), $ACCEL"
# one modprobe for the drivers that need no parameters, USB first: it enumerates meanwhile
modprobe -a xhci_pci ftdi_sio vcan kvaser_pci i2c-dev uinput evdev gpio-sim rtloop_spi_loopback 2>/dev/null
setup_vcan
setup_can
setup_i2c
setup_uinput
setup_gpio
setup_spi
setup_serial
{
    printf '{\n  "kernel": %s,\n  "accel": "%s",\n  "devices": {\n' "$(json_string "$(uname -r)")" "$ACCEL"
    for index in "${!entries[@]}"; do
        printf '    %s%s\n' "${entries[$index]}" "$([ "$index" -lt $((${#entries[@]} - 1)) ] && echo ,)"
    done
    printf '  }\n}\n'
} > "$map"

# --- the command -------------------------------------------------------------------------------
export RTLOOP_GUEST=1 RTLOOP_GUEST_DEVICES=$map RTLOOP_GUEST_ACCEL=$ACCEL
# how much slower than the host Python runs here: real-time tests stretch periods and durations by it
export RTLOOP_TEST_SLOWDOWN=${SLOWDOWN:-$([ "$ACCEL" = tcg ] && echo 20 || echo 1)}
# starting a task process (Python, numpy, mlockall) takes that much longer too
export RTLOOP_STARTUP_ALLOWANCE_S=$((30 * ${RTLOOP_TEST_SLOWDOWN%.*}))
# pytest runs serially here, by hand too (pyproject.toml's addopts run the host suite in 3 processes;
# tests/conftest.py then takes those options and ignores them)
export PYTEST_ADDOPTS="-p no:xdist${PYTEST_ADDOPTS:+ $PYTEST_ADDOPTS}"
[ -d "$PROJECT/.venv/bin" ] && export PATH="$PROJECT/.venv/bin:$PATH" VIRTUAL_ENV="$PROJECT/.venv"
mapfile -d '' argv < "$ctl/argv"
cd "$PROJECT" || { say "no $PROJECT"; power_off; }
say "running: ${argv[*]}"
: > "$ctl/started"   # from here on, a guest that stops without a status has failed the command
"${argv[@]}" < /dev/null
status=$?
echo "$status" > "$ctl/status"
power_off
