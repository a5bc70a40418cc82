"""Bad input to an EtherCAT drive device: one line naming the key, exit 2 before anything starts
(exit 3 for an interface that is not there). No bus needed: the app file is refused as it loads,
or the interface is found missing by the device's check."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from drive_veth import example_app
from rtloop.app.builder import App
from rtloop.errors import DeviceError
from rtloop.io.drives.emulator import DEFAULT_IDENTITY

PAN = "gear_ratio = 19.0\n"  # the pan joint's line (the first joint): a key added after it is the pan's
PAN_MODE = 'mode = "csp"\ncounts_per_rev = 4096            #'


def _rtloop(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rtloop", *args], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize(("replace", "words"), [
    ({PAN_MODE: PAN_MODE.replace('"csp"', '"pp"')},
     "devices.gimbal.joints[0].mode: 'pp' is not a mode rtloop drives"),
    ({PAN: PAN + 'rxpdo = ["0x6040", "0x6060", "0x60FF"]\n'},
     "devices.gimbal.joints[0].rxpdo: mode csp needs object 0x607A (target position) in the mapping; it is missing"),
    ({PAN: PAN + 'txpdo = ["0x6064", "0x606C"]\n'},
     "devices.gimbal.joints[0].txpdo: object 0x6041 (statusword) is missing from the mapping"),
    ({PAN: PAN + 'rxpdo = ["0x6040", "0x6060", "0x607A", "0x2000"]\n'},
     "devices.gimbal.joints[0].rxpdo[3]: object 0x2000 is not one rtloop maps"),
    ({PAN: PAN + 'rxpdo = ["0x6040", "0x6041"]\n'},
     "devices.gimbal.joints[0].rxpdo[1]: 0x6041 (statusword) does not go in the RxPDO"),
    ({PAN_MODE: PAN_MODE.replace("4096", "0")},
     "devices.gimbal.joints[0]: counts_per_rev must be > 0"),
    ({"kp_Nm_per_rad = 2.842e-4": "kp_Nm_per_rad = 2.842e-4\nspring = 3.0"},
     "devices.gimbal.joints[0].drive.spring: unknown"),
    # a count's radians underflowed to 0.0: the first command divided by zero in the loop (a traceback)
    ({PAN_MODE: PAN_MODE.replace("4096", "1e308")},
     "devices.gimbal.joints[0]: counts_per_rev must be a whole number 1..4294967296, got 1e+308"),
    ({PAN: "gear_ratio = 1e308\n"}, "devices.gimbal.joints[0]: gear_ratio must be 1e-06..1e+06"),
    # the drive model counted 2, the device 2.5
    ({PAN_MODE: PAN_MODE.replace("4096", "2.5")}, "devices.gimbal.joints[0]: counts_per_rev must be a whole number"),
    ({PAN_MODE: PAN_MODE.replace('"csp"', '["csp"]')},
     "devices.gimbal.joints[0].mode: ['csp'] is not a mode rtloop drives"),
    ({PAN_MODE: PAN_MODE.replace('mode = "csp"', 'modes = ["csp", "csp"]')},
     "devices.gimbal.joints[0].modes: 'csp' is listed twice"),
])
def test_a_joint_table_that_cannot_be_driven_is_refused_as_the_app_loads(tmp_path: Path, replace: dict[str, str],
                                                                          words: str) -> None:
    app = example_app(tmp_path, "ecm9", "ecs9", "ecat_bad", **replace)
    result = _rtloop("simulate", str(app), "--duration", "1", "--out", str(tmp_path / "sim"), "-q")
    assert result.returncode == 2, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert words in result.stderr, result.stderr
    assert not (tmp_path / "sim").exists()


def test_an_interface_that_does_not_exist_is_a_bus_not_ready(tmp_path: Path) -> None:
    pytest.importorskip("pysoem")
    app = example_app(tmp_path, "nosuchif7", "ecs7", "ecat_noif")
    result = _rtloop("run", str(app), "--duration", "1", "--out", str(tmp_path / "run"), "-q")
    assert result.returncode == 3, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert "devices.gimbal.interface: no network interface 'nosuchif7' here" in result.stderr


def test_process_data_that_does_not_fit_one_frame_is_refused() -> None:
    joint = {"vendor": DEFAULT_IDENTITY.vendor, "product": DEFAULT_IDENTITY.product,
             "revision": DEFAULT_IDENTITY.revision, "mode": "csp", "counts_per_rev": 4096}
    app = _app()
    with pytest.raises(DeviceError, match="does not fit in one frame"):
        app.add_device("arm", "ethercat", task="ctl", interface="ecm0",
                       joints=[{"name": f"j{i}", **joint} for i in range(60)])


ESI = """<?xml version="1.0"?>
<EtherCATInfo>
  <Vendor><Id>#x00000A7E</Id><Name>rtloop</Name></Vendor>
  <Descriptions><Devices><Device>
    <Type ProductCode="#x00402402" RevisionNo="#x00010000">drive</Type>
    <RxPdo Sm="2"><Index>#x1600</Index>
      <Entry><Index>#x6040</Index><SubIndex>0</SubIndex><BitLen>16</BitLen></Entry>
      <Entry><Index>#x6060</Index><SubIndex>0</SubIndex><BitLen>8</BitLen></Entry>
      <Entry><Index>#x607A</Index><SubIndex>0</SubIndex><BitLen>32</BitLen></Entry>
    </RxPdo>
    <TxPdo Sm="3"><Index>#x1A00</Index>
      <Entry><Index>#x6041</Index><SubIndex>0</SubIndex><BitLen>16</BitLen></Entry>
      <Entry><Index>#x6064</Index><SubIndex>0</SubIndex><BitLen>32</BitLen></Entry>
    </TxPdo>
  </Device></Devices></Descriptions>
</EtherCATInfo>
"""


def _app() -> App:
    from rtloop import Runnable

    class Ctl(Runnable):
        n_inputs, n_outputs = 0, 0

        def step(self, u: object, y: object) -> None:
            pass

    app = App("ecat_esi")
    app.add_task("ctl", Ctl(), period_ns=1_000_000)
    return app


def test_an_esi_file_gives_the_identity_and_the_mapping(tmp_path: Path) -> None:
    (tmp_path / "drive.xml").write_text(ESI)
    spec = _app().add_device("arm", "ethercat", task="ctl", interface="ecm0", esi_dir=str(tmp_path),
                             joints=[{"name": "pan", "esi": "drive.xml", "mode": "csp", "counts_per_rev": 4096}])
    joint = spec.device.joints[0]
    assert joint.identity == DEFAULT_IDENTITY
    assert joint.rx.objects == (0x6040, 0x6060, 0x607A) and joint.tx.objects == (0x6041, 0x6064)
    assert spec.device.output_names == ("pan_position_rad", "pan_enabled", "pan_fault", "pan_warning",
                                        "pan_target_reached", "pan_following_error", "pan_quick_stop")


def test_an_esi_file_that_does_not_parse_is_named(tmp_path: Path) -> None:
    (tmp_path / "drive.xml").write_text("<EtherCATInfo><Vendor>")
    with pytest.raises(DeviceError, match=r"joints\[0\]\.esi: .*drive.xml: cannot read it as an ESI file"):
        _app().add_device("arm", "ethercat", task="ctl", interface="ecm0", esi_dir=str(tmp_path),
                          joints=[{"name": "pan", "esi": "drive.xml", "counts_per_rev": 4096}])


def _esi_joint_refused(tmp_path: Path, esi: str, words: str) -> None:
    with pytest.raises(DeviceError, match=words):
        _app().add_device("arm", "ethercat", task="ctl", interface="ecm0", esi_dir=str(tmp_path),
                          joints=[{"name": "pan", "esi": esi, "mode": "csp", "counts_per_rev": 4096}])


def test_an_esi_files_entities_are_refused_not_expanded_or_fetched(tmp_path: Path) -> None:
    laughs = "".join(f'<!ENTITY l{i} "{f"&l{i - 1};" * 10 if i else "lol"}">' for i in range(10))
    (tmp_path / "laughs.xml").write_text(f'<?xml version="1.0"?><!DOCTYPE x [{laughs}]>\n'
                                         + ESI.split("\n", 1)[1].replace("rtloop</Name>", "&l9;</Name>"))
    _esi_joint_refused(tmp_path, "laughs.xml", r"joints\[0\]\.esi: .*laughs.xml: cannot read it as an ESI file "
                       r"\(it declares the entity 'l0'; an ESI file has no DTD entities")
    (tmp_path / "outside.xml").write_text('<?xml version="1.0"?><!DOCTYPE x [<!ENTITY e SYSTEM "file:///etc/passwd">]>'
                                          + ESI.split("\n", 1)[1].replace("rtloop</Name>", "&e;</Name>"))
    _esi_joint_refused(tmp_path, "outside.xml",
                       r"outside.xml: cannot read it as an ESI file \(it declares the entity 'e'")


def test_an_esi_path_that_is_no_regular_file_or_too_large_is_refused_without_reading_it(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo.xml"  # opened, it would block the load forever
    os.mkfifo(fifo)
    _esi_joint_refused(tmp_path, "fifo.xml", r"joints\[0\]\.esi: .*fifo.xml: not a regular file, so not an ESI file")
    (tmp_path / "zero.xml").symlink_to("/dev/zero")
    _esi_joint_refused(tmp_path, "zero.xml", r"zero.xml: not a regular file")
    (tmp_path / "folder.xml").mkdir()
    _esi_joint_refused(tmp_path, "folder.xml", r"folder.xml: not a regular file")
    with (tmp_path / "huge.xml").open("wb") as huge:
        huge.truncate(2 << 30)  # sparse: 2 GB that take no disk
    _esi_joint_refused(tmp_path, "huge.xml",
                       r"huge.xml: 2147483648 bytes, more than an ESI file rtloop reads \(32 MiB\)")


def test_an_esi_identity_past_32_bits_is_refused(tmp_path: Path) -> None:
    (tmp_path / "wide.xml").write_text(ESI.replace("#x00000A7E", "#x1FFFFFFFF"))
    _esi_joint_refused(tmp_path, "wide.xml", r"wide.xml: not an ESI file rtloop reads \(its vendor 8589934591 is not "
                       r"a 32-bit number\)")
    (tmp_path / "negative.xml").write_text(ESI.replace("#x00000A7E", "-5"))
    _esi_joint_refused(tmp_path, "negative.xml", r"its vendor -5 is not a 32-bit number")


def test_two_drive_devices_on_one_interface_are_refused() -> None:
    joint = {"vendor": DEFAULT_IDENTITY.vendor, "product": DEFAULT_IDENTITY.product,
             "revision": DEFAULT_IDENTITY.revision, "mode": "csp", "counts_per_rev": 4096}
    app = _app()
    app.add_device("arm", "ethercat", task="ctl", interface="ecm0", joints=[{"name": "a", **joint}])
    with pytest.raises(DeviceError, match=r"devices.legs.interface: EtherCAT segment clash: ecm0 is also held by "
                                          r"devices.arm.interface"):
        app.add_device("legs", "ethercat", task="ctl", interface="ecm0", joints=[{"name": "b", **joint}])
