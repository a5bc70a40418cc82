"""The trust boundary of a running app (docs/security.md): /dev/shm and the app file's folder.

The tests with a second local user create one with useradd (as root) and remove it after;
without root they are skipped, saying so.
"""

from __future__ import annotations

import json
import os
import pickle
import pwd
import re
import secrets
import stat
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from rtloop.app.appfile import load_app
from rtloop.errors import AppFileError
from rtloop.ipc.ports import AppNotReachable, AppNotRunning, app_from_registry, connect_app, running_apps
from rtloop.ipc.segments import Segment, SegmentRefused, check_segment_name, new_run_token
from rtloop.sudo import trusted_users_phrase

SHM = Path("/dev/shm")
NOBODY_UID = 65534
ROOT = os.geteuid() == 0
needs_root = pytest.mark.skipif(not ROOT, reason="needs root: to create a second user and to chown files")


def _name(what: str) -> str:
    return f"rtloop-trust{os.getpid()}-{os.getpid()}-{new_run_token()}-{what}"


@pytest.fixture
def shm_files() -> Iterator[list[Path]]:
    made: list[Path] = []
    yield made
    for path in made:
        path.unlink(missing_ok=True)


# --- names, links, owners ---------------------------------------------------------------------
@pytest.mark.parametrize("bad", ["../../etc/passwd", "rtloop-a-1-00000000-../x", "rtloop-a-1-00000000-x/y",
                                 "/dev/shm/rtloop-a-1-00000000-x", "rtloop-a-1-0000000-x", "", "x" * 300])
def test_segment_names_outside_the_pattern_are_refused(bad: str) -> None:
    with pytest.raises(SegmentRefused, match="not an rtloop segment name"):
        check_segment_name(bad)
    with pytest.raises(SegmentRefused):
        Segment.attach(bad)


def test_a_symbolic_link_in_dev_shm_is_never_followed(tmp_path: Path, shm_files: list[Path]) -> None:
    target = tmp_path / "precious"
    target.write_bytes(b"\0" * 64)
    link = SHM / _name("port.x")
    link.symlink_to(target)
    shm_files.append(link)
    with pytest.raises(SegmentRefused, match="symbolic link"):
        Segment.attach(link.name)
    with pytest.raises(FileExistsError):  # O_EXCL: a planted link blocks creation, it is not written through
        Segment(link.name, 64, create=True)
    assert target.read_bytes() == b"\0" * 64


def test_a_fifo_is_not_a_segment(shm_files: list[Path]) -> None:
    fifo = SHM / _name("port.fifo")
    os.mkfifo(fifo, 0o600)
    shm_files.append(fifo)
    with pytest.raises(SegmentRefused, match="not a regular file"):
        Segment.attach(fifo.name)


def test_segments_are_created_0600_and_exclusive(shm_files: list[Path]) -> None:
    segment = Segment.create("trust", os.getpid(), new_run_token(), "mode", 64)
    shm_files.append(segment.path)
    assert stat.S_IMODE(segment.path.stat().st_mode) == 0o600
    with pytest.raises(FileExistsError):
        Segment(segment.name, 64, create=True)
    segment.close()


@needs_root
def test_a_segment_of_another_owner_is_refused_saying_whose(shm_files: list[Path]) -> None:
    segment = Segment.create("trust", os.getpid(), new_run_token(), "owned", 64)
    shm_files.append(segment.path)
    os.chown(segment.path, NOBODY_UID, NOBODY_UID)
    with pytest.raises(SegmentRefused, match=f"owned by uid {NOBODY_UID}, not by the app's uid 0"):
        Segment.attach(segment.name, owner_uid=0)
    Segment.attach(segment.name).close()  # without an owner to check (tests, tools), it maps


def _plant_registry(name: str, app: str, pid: int, ports: dict, directory: Path = SHM) -> Path:
    path = directory / f"rtloop-{app}-{pid}-{new_run_token()}-registry.json"
    path.write_text(json.dumps({"app": app, "pid": pid, "ports": ports, "tasks": {}, "control": None}))
    return path


@needs_root
def test_a_registry_not_owned_by_its_supervisors_uid_is_refused(shm_files: list[Path]) -> None:
    app = f"claimed{os.getpid()}"
    path = _plant_registry("", app, 1, {})  # pid 1 runs as root; the file will belong to nobody
    shm_files.append(path)
    os.chown(path, NOBODY_UID, NOBODY_UID)
    with pytest.raises(SegmentRefused, match=f"owned by uid {NOBODY_UID}, but its supervisor pid 1 runs as uid 0"):
        app_from_registry(path)
    assert app not in {a.name for a in running_apps()}
    with pytest.raises(AppNotReachable, match=r"registry refused: .*owned by uid"):
        connect_app(app)


def test_a_registry_whose_content_names_another_app_is_refused(shm_files: list[Path]) -> None:
    path = SHM / f"rtloop-mine{os.getpid()}-{os.getpid()}-{new_run_token()}-registry.json"
    path.write_text(json.dumps({"app": "other", "pid": os.getpid(), "ports": {}, "tasks": {}}))
    shm_files.append(path)
    with pytest.raises(SegmentRefused, match="its content names app 'other'"):
        app_from_registry(path)


def test_a_registry_pointing_outside_dev_shm_is_never_written_through(tmp_path: Path, shm_files: list[Path]) -> None:
    victim = tmp_path / "root-only"
    victim.write_bytes(b"\0" * 256)
    app = f"escape{os.getpid()}"
    escape = os.path.relpath(victim, SHM)
    port = {"direction": "in", "segment": escape, "signal": "t.u[0]", "size": 1, "allow_nonfinite": False,
            "period_ns": 1_000_000}
    shm_files.append(_plant_registry("", app, os.getpid(), {"p": port}))
    running = connect_app(app)
    with pytest.raises(SegmentRefused, match="not a segment of that run"):
        running.write("p", [1.0])
    assert victim.read_bytes() == b"\0" * 256


def test_no_running_app_is_said_plainly() -> None:
    with pytest.raises(AppNotRunning, match="no running app named 'nothing_here_"):
        connect_app(f"nothing_here_{secrets.token_hex(3)}")


@needs_root
def test_root_acts_on_another_users_app_only_when_it_says_so(shm_files: list[Path]) -> None:
    sleeper = subprocess.Popen(["sleep", "60"], user=NOBODY_UID, group=NOBODY_UID)
    try:
        app = f"users{os.getpid()}"
        path = _plant_registry("", app, sleeper.pid, {})
        shm_files.append(path)
        os.chown(path, NOBODY_UID, NOBODY_UID)
        deadline = time.monotonic() + 10  # /proc shows the new uid once the child has switched
        while time.monotonic() < deadline and not any(a.name == app for a in running_apps()):
            time.sleep(0.05)
        with pytest.raises(AppNotReachable, match=rf"runs as uid {NOBODY_UID}, not as uid 0.*--user"):
            connect_app(app)
        assert connect_app(app, owner_uid=NOBODY_UID).uid == NOBODY_UID
    finally:
        sleeper.kill()
        sleeper.wait()


# --- the app file's folder --------------------------------------------------------------------
def _app_toml(folder: Path, name: str, runnable: str) -> Path:
    path = folder / f"{name}.toml"
    path.write_text(f'name = "{name}"\n[tasks.t]\nrunnable = "{runnable}"\nperiod_ns = 1_000_000\n')
    return path


def test_the_module_beside_the_app_file_is_loaded_by_path_and_reaches_task_processes(tmp_path: Path) -> None:
    module = f"beside_{secrets.token_hex(4)}"
    (tmp_path / f"{module}.py").write_text(textwrap.dedent("""
        from rtloop import Runnable

        class Here(Runnable):
            n_inputs = 0
            n_outputs = 1

            def __init__(self, gain=2.0):
                self.gain = gain

            def step(self, u, y):
                y[0] = self.gain
    """))
    (tmp_path / "json.py").write_text("raise SystemExit('the folder shadowed the json module')\n")
    app = load_app(_app_toml(tmp_path, "beside", f"{module}:Here"))
    assert str(tmp_path) not in sys.path
    payload = pickle.dumps(app.tasks["t"].runnable)
    # a fresh interpreter, as a spawned task process is: unpickling loads the module by path, not json.py
    code = "import pickle, sys, json; r = pickle.loads(sys.stdin.buffer.read()); print(type(r).__name__, r.gain)"
    done = subprocess.run([sys.executable, "-c", code], input=payload, capture_output=True, cwd="/")
    assert done.returncode == 0, done.stderr.decode()
    assert done.stdout.decode().split() == ["Here", "2.0"]


def test_a_module_beside_the_app_file_never_shadows_an_installed_one(tmp_path: Path) -> None:
    (tmp_path / "rt_test_runnables.py").write_text("raise SystemExit('shadow ran')\n")
    with pytest.raises(AppFileError, match="would shadow the installed module 'rt_test_runnables'"):
        load_app(_app_toml(tmp_path, "shadow", "rt_test_runnables:Noop"))


def test_other_modules_in_the_folder_are_not_importable(tmp_path: Path) -> None:
    marker = tmp_path / "ran"
    (tmp_path / "numpy.py").write_text(f"open({str(marker)!r}, 'w').close()\n")
    app = load_app(_app_toml(tmp_path, "installed", "rt_test_runnables:Noop"))
    import rtloop

    rtloop.simulate(app, 0.01, tmp_path / "out")
    assert not marker.exists()


# --- a second local user plants a registry, a segment and a module ----------------------------
def _python_for_anyone() -> str:
    """An interpreter of this Python version that any user may run (a venv's may live in /root)."""
    import shutil

    version = f"python{sys.version_info.major}.{sys.version_info.minor}"
    for candidate in (sys.executable, shutil.which(version, path="/usr/bin:/bin:/usr/local/bin")):
        if candidate and all(os.stat(p).st_mode & 0o001 for p in _path_and_parents(Path(candidate).resolve())):
            return candidate
    pytest.skip(f"no {version} that another user may run (this one lives in a private folder)")


def _path_and_parents(path: Path) -> list[Path]:
    return [path, *path.parents]


@pytest.fixture(scope="module")
def second_user() -> Iterator[pwd.struct_passwd]:
    if not ROOT:
        pytest.skip("needs root to create a second local user (useradd)")
    name = f"rtl{secrets.token_hex(3)}"
    created = subprocess.run(["useradd", "--no-create-home", "--shell", "/usr/sbin/nologin", name],
                             capture_output=True, text=True)
    if created.returncode != 0:
        pytest.skip(f"useradd failed: {created.stderr.strip()}")
    try:
        user = pwd.getpwnam(name)
        probe = _as(user, "import numpy, rtloop.cli.main", {"PATH": os.environ.get("PATH", "")})
        if probe.returncode != 0:
            pytest.skip("another local user cannot import rtloop and numpy here (installed under a folder "
                        f"only root may enter): {probe.stderr.strip().splitlines()[-1:]}")
        yield user
    finally:
        subprocess.run(["userdel", name], capture_output=True)


def _env_for_anyone(env: dict[str, str]) -> dict[str, str]:
    """``env`` plus this interpreter's packages (numpy) on PYTHONPATH, for another user's interpreter."""
    import numpy

    import rtloop

    site = str(Path(numpy.__file__).parent.parent)
    source = str(Path(rtloop.__file__).parent.parent)  # an editable install is a .pth file PYTHONPATH skips
    paths = [env.get("PYTHONPATH", ""), source, site]
    return {**env, "PYTHONPATH": os.pathsep.join(p for p in paths if p)}


def _as(user: pwd.struct_passwd, code: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run([_python_for_anyone(), "-c", code], user=user.pw_uid, group=user.pw_gid,
                          env=_env_for_anyone(env), capture_output=True, text=True, cwd="/", timeout=60)


def _rtloop(args: list[str], env: dict[str, str], **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rtloop.cli", *args], env=env, capture_output=True, text=True,
                          timeout=120, **kwargs)


def test_second_user_plants_a_registry_and_a_segment_root_refuses(second_user, tmp_path: Path, rtloop_env) -> None:
    victim = tmp_path / "root-only"
    victim.write_bytes(b"\0" * 256)
    victim.chmod(0o600)
    app = f"victim{os.getpid()}"
    token = new_run_token()
    plant = textwrap.dedent(f"""
        import json, os, subprocess, time
        sleeper = subprocess.Popen(["sleep", "60"])  # a live process of this user: a plausible supervisor
        for pid, segment in ((1, {os.path.relpath(victim, SHM)!r}), (sleeper.pid, None)):
            prefix = f"rtloop-{app}-{{pid}}-{token}-"
            segment = segment or prefix + "port.p"
            if segment.startswith("rtloop-"):  # a valid one-value port: header words, then the value
                with open("/dev/shm/" + segment, "wb") as f:
                    f.write(bytes(24) + (1).to_bytes(8, "little") + bytes(40))
            port = {{"direction": "in", "segment": segment, "signal": "t.u[0]", "size": 1,
                     "allow_nonfinite": False, "period_ns": 1000000}}
            with open("/dev/shm/" + prefix + "registry.json", "w") as f:
                json.dump({{"app": "{app}", "pid": pid, "ports": {{"p": port}}, "tasks": {{}}}}, f)
        print(sleeper.pid, flush=True)
        time.sleep(60)
    """)
    planter = subprocess.Popen([_python_for_anyone(), "-c", plant], user=second_user.pw_uid,
                               group=second_user.pw_gid, env=_env_for_anyone(rtloop_env), stdout=subprocess.PIPE,
                               text=True, cwd="/")
    try:
        sleeper_pid = int(planter.stdout.readline())
        time.sleep(0.2)
        done = _rtloop(["port", "write", app, "p", "1.5"], rtloop_env)
        assert done.returncode == 2, done.stderr
        assert "Traceback" not in done.stderr
        assert f"runs as uid {second_user.pw_uid}, not as uid 0" in done.stderr, done.stderr
        assert victim.read_bytes() == b"\0" * 256
        # as root on purpose: the planted app of that user is reachable, but its segment is theirs
        on_purpose = _rtloop(["port", "write", app, "p", "1.5", "--user", str(second_user.pw_uid)], rtloop_env)
        assert on_purpose.returncode == 0, on_purpose.stderr
        assert victim.read_bytes() == b"\0" * 256  # the pid-1 registry (pointing at it) was never believed
        os.kill(sleeper_pid, 9)
    finally:
        planter.kill()
        planter.communicate()
        for path in SHM.glob(f"rtloop-{app}-*"):
            path.unlink(missing_ok=True)


def test_second_user_cannot_reach_roots_app_and_is_told_why(second_user, tmp_path: Path, rtloop_env) -> None:
    name = f"rootapp{os.getpid()}"
    app_file = _app_toml(tmp_path, name, "rt_test_runnables:Noop")
    runner = subprocess.Popen([sys.executable, "-m", "rtloop.cli", "run", str(app_file), "--duration", "200",
                               "--out", str(tmp_path / "out"), "-q"], env=rtloop_env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        connect_app(name, timeout_s=60)
        code = ("import sys; from rtloop.cli.main import main; "
                f"sys.exit(main(['port', 'read', {name!r}, 'x', '--count', '1']))")
        done = _as(second_user, code, rtloop_env)
        assert done.returncode == 2, done.stderr
        assert "Traceback" not in done.stderr
        assert f"permission denied (owned by uid 0; you are uid {second_user.pw_uid})" in done.stderr, done.stderr
        assert "no running app" not in done.stderr
    finally:
        runner.terminate()
        runner.communicate(timeout=60)


@pytest.fixture
def open_dir() -> Iterator[Path]:
    """A folder every user may write to, like /tmp (pytest's own tmp_path is root's alone)."""
    import shutil
    import tempfile

    folder = Path(tempfile.mkdtemp(prefix="rtloop-trust-"))
    folder.chmod(0o1777)
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def test_second_user_plants_modules_in_the_app_folder_and_none_runs(second_user, open_dir: Path, tmp_path: Path,
                                                                    rtloop_env) -> None:
    folder = open_dir
    marker = open_dir / "planted-ran"
    module = f"planted_{secrets.token_hex(3)}"
    plant = textwrap.dedent(f"""
        for name in ("numpy.py", "rtloop.py", "{module}.py"):
            with open("{folder}/" + name, "w") as f:
                f.write("open({str(marker)!r}, 'w').close()\\n")
    """)
    assert _as(second_user, plant, rtloop_env).returncode == 0
    installed = _app_toml(folder, f"inst{os.getpid()}", "rt_test_runnables:Noop")
    done = _rtloop(["simulate", str(installed), "--duration", "0.01", "--out", str(tmp_path / "o1"), "-q"], rtloop_env)
    assert done.returncode == 0, done.stderr
    named = _app_toml(folder, f"named{os.getpid()}", f"{module}:Noop")
    refused = _rtloop(["simulate", str(named), "--duration", "0.01", "--out", str(tmp_path / "o2"), "-q"], rtloop_env)
    assert refused.returncode == 2, refused.stderr
    # root, or under sudo the user who ran it (tools/as-root in their own clone): whom rtloop trusts
    assert f"is owned by uid {second_user.pw_uid}, not by {trusted_users_phrase()}" in refused.stderr
    assert "Traceback" not in refused.stderr
    assert not marker.exists(), "a module planted by another user ran as root"


# --- bytecode and the folders code is loaded from (B5) ----------------------------------------
PLANTED_PYC_MODULE = textwrap.dedent("""
    from rtloop import Runnable

    class Here(Runnable):
        n_inputs, n_outputs = 0, 1

        def step(self, u, y):
            y[0] = 1.0
""")


def _plant_bytecode(source: Path, code: str, owner_uid: int) -> None:
    """A valid ``__pycache__`` entry for ``source`` (its mtime and size in the header) holding ``code``."""
    import importlib.util
    import marshal

    facts = source.stat()
    cached = Path(importlib.util.cache_from_source(str(source)))
    cached.parent.mkdir(exist_ok=True)
    header = importlib.util.MAGIC_NUMBER + (0).to_bytes(4, "little") + \
        (int(facts.st_mtime) & 0xFFFFFFFF).to_bytes(4, "little") + (facts.st_size & 0xFFFFFFFF).to_bytes(4, "little")
    cached.write_bytes(header + marshal.dumps(compile(code, str(source), "exec")))
    for path in (cached.parent, cached):
        os.chown(path, owner_uid, owner_uid)


@needs_root
def test_bytecode_planted_beside_a_roots_module_never_runs(tmp_path: Path) -> None:
    folder = tmp_path / "app"
    folder.mkdir()
    module = f"bytecode_{secrets.token_hex(3)}"
    source = folder / f"{module}.py"
    source.write_text(PLANTED_PYC_MODULE)
    marker = tmp_path / "planted-ran"
    _plant_bytecode(source, f"open({str(marker)!r}, 'w').close()\n" + PLANTED_PYC_MODULE, NOBODY_UID)
    app = load_app(_app_toml(folder, f"pyc{os.getpid()}", f"{module}:Here"))
    assert not marker.exists(), "bytecode planted by another user ran as root"
    assert type(app.tasks["t"].runnable).__name__ == "Here"
    # a fresh interpreter, as a task process is, loads the module again: from its source too
    payload = pickle.dumps(app.tasks["t"].runnable)
    done = subprocess.run([sys.executable, "-c", "import pickle, sys; pickle.loads(sys.stdin.buffer.read())"],
                          input=payload, capture_output=True, cwd="/")
    assert done.returncode == 0, done.stderr.decode()
    assert not marker.exists(), "bytecode planted by another user ran as root in a task process"


def test_loading_a_module_beside_the_app_file_writes_no_bytecode(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys, "dont_write_bytecode", False)  # as a plain python (tools/as-root sets it)
    module = f"nocache_{secrets.token_hex(3)}"
    (tmp_path / f"{module}.py").write_text(PLANTED_PYC_MODULE)
    load_app(_app_toml(tmp_path, f"nocache{os.getpid()}", f"{module}:Here"))
    assert not (tmp_path / "__pycache__").exists()  # root's bytecode would litter a sudo user's folder


@needs_root
@pytest.mark.parametrize(("owner", "mode", "says"), [
    (NOBODY_UID, 0o755, f"owned by uid {NOBODY_UID}"),
    (0, 0o777, "writable by every user"),
    (0, 0o775, f"writable by group {NOBODY_UID}"),
])
def test_an_app_folder_another_user_may_write_is_refused(tmp_path: Path, rtloop_env, owner: int, mode: int,
                                                         says: str) -> None:
    folder = tmp_path / "app"
    folder.mkdir()
    module = f"swapme_{secrets.token_hex(3)}"
    (folder / f"{module}.py").write_text(PLANTED_PYC_MODULE)
    app_file = _app_toml(folder, f"fold{os.getpid()}", f"{module}:Here")
    os.chown(folder, owner, NOBODY_UID)  # group nogroup: its members are not you
    folder.chmod(mode)
    with pytest.raises(AppFileError, match=f"{folder}.*{says}"):
        load_app(app_file)
    done = _rtloop(["simulate", str(app_file), "--duration", "0.01", "--out", str(tmp_path / "o"), "-q"],
                   rtloop_env)
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and says in done.stderr, done.stderr


@needs_root
def test_a_parent_folder_another_user_owns_is_refused(tmp_path: Path) -> None:
    parent = tmp_path / "theirs"
    folder = parent / "app"
    folder.mkdir(parents=True)
    module = f"parent_{secrets.token_hex(3)}"
    (folder / f"{module}.py").write_text(PLANTED_PYC_MODULE)
    os.chown(parent, NOBODY_UID, NOBODY_UID)  # they may rename app/ away and put their own in its place
    with pytest.raises(AppFileError, match=f"{parent} is owned by uid {NOBODY_UID}"):
        load_app(_app_toml(folder, f"par{os.getpid()}", f"{module}:Here"))


def test_a_user_writing_to_roots_app_is_told_to_run_as_root(second_user, rtloop_env) -> None:
    name = f"asroot{os.getpid()}"
    sleeper = subprocess.Popen(["sleep", "60"])  # a live root process: the supervisor the registry names
    registry = _live_registry(name, sleeper.pid)
    code = ("import sys; from rtloop.cli.main import main; "
            f"sys.exit(main(['port', 'write', {name!r}, 'gains', '0.08', '4.0']))")
    try:
        done = _as(second_user, code, rtloop_env)
        assert done.returncode == 2, done.stderr
        assert len(done.stderr.strip().splitlines()) == 1, done.stderr
        assert f"app {name!r} runs as root" in done.stderr, done.stderr
        assert re.search(r"\((/\S+/tools/as-root|sudo) /\S+ (-m rtloop )?port \.\.\.\)", done.stderr), done.stderr
    finally:
        sleeper.kill()
        sleeper.wait()
        registry.unlink(missing_ok=True)


def test_top_as_a_user_says_an_app_runs_as_root_not_that_none_runs(second_user, rtloop_env) -> None:
    name = f"toproot{os.getpid()}"
    sleeper = subprocess.Popen(["sleep", "60"])  # a live root process: the supervisor the registry names
    registry = _live_registry(name, sleeper.pid)
    try:
        for args in (["top", name, "--once"], ["top", name], ["top", "--once"]):
            code = f"import sys; from rtloop.cli.main import main; sys.exit(main({args!r}))"
            done = _as(second_user, code, rtloop_env)
            assert done.returncode == 2, (args, done.stderr)
            assert len(done.stderr.strip().splitlines()) == 1, done.stderr
            assert f"app {name!r} runs as root: run rtloop top as root too" in done.stderr, (args, done.stderr)
            assert re.search(r"\((/\S+/tools/as-root|sudo) /\S+ (-m rtloop )?top \.\.\.\)", done.stderr), done.stderr
    finally:
        sleeper.kill()
        sleeper.wait()
        registry.unlink(missing_ok=True)


def test_switch_and_reload_as_a_user_name_themselves_when_the_app_runs_as_root(second_user, rtloop_env) -> None:
    # they said "run rtloop port as root too (… rtloop port ...)": the user ran rtloop switch
    name = f"swroot{os.getpid()}"
    sleeper = subprocess.Popen(["sleep", "60"])  # a live root process: the supervisor the registry names
    registry = _live_registry(name, sleeper.pid)
    try:
        for command, args in (("switch", ["switch", name, "controller", "soft"]),
                              ("reload", ["reload", name, "controller", "pid"])):
            code = f"import sys; from rtloop.cli.main import main; sys.exit(main({args!r}))"
            done = _as(second_user, code, rtloop_env)
            assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
            assert f"app {name!r} runs as root: run rtloop {command} as root too" in done.stderr, done.stderr
            assert re.search(rf"\((/\S+/tools/as-root|sudo) /\S+ (-m rtloop )?{command} \.\.\.\)", done.stderr), \
                done.stderr
    finally:
        sleeper.kill()
        sleeper.wait()
        registry.unlink(missing_ok=True)


def test_a_root_registry_left_by_a_dead_supervisor_is_not_an_app_that_runs(second_user, rtloop_env) -> None:
    name = f"topgone{os.getpid()}"
    gone = subprocess.Popen(["true"])
    gone.wait()  # its pid names no process now
    registry = _live_registry(name, gone.pid)
    try:
        for args in (["top", name, "--once"], ["port", "write", name, "gains", "1"]):
            code = f"import sys; from rtloop.cli.main import main; sys.exit(main({args!r}))"
            done = _as(second_user, code, rtloop_env)
            assert done.returncode == 2 and f"no running app named {name!r}" in done.stderr, (args, done.stderr)
    finally:
        registry.unlink(missing_ok=True)


def test_top_draws_a_line_for_each_app_of_another_user() -> None:
    from rich.console import Console

    from rtloop.cli.top_view import render

    line = "app 'x' runs as root: run rtloop top as root too (tools/as-root .venv/bin/rtloop top ...)"
    console = Console(width=200, record=True)
    console.print(render([], 200, [line]))
    assert line in console.export_text()
    console.print(render([], 200, []))
    assert "no running rtloop app found" in console.export_text()


def _live_registry(name: str, pid: int) -> Path:
    path = SHM / f"rtloop-{name}-{pid}-{new_run_token()}-registry.json"
    fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
    with os.fdopen(fd, "w") as file:
        json.dump({"app": name, "pid": pid, "mode": "run", "ports": {}, "tasks": {}}, file)
    return path


@pytest.fixture
def roots_dcmotor() -> Iterator[Path]:
    """The DC motor example copied into a folder of root's that every user may read: the example in a
    clone a sudo user owns is theirs, and a second user's rtloop rightly runs none of their code."""
    import shutil
    import tempfile

    folder = Path(tempfile.mkdtemp(prefix="rtloop-dcmotor-"))
    folder.chmod(0o755)
    shutil.copytree(Path(__file__).parents[1] / "examples" / "dcmotor", folder / "dcmotor",
                    ignore=shutil.ignore_patterns("__pycache__"))
    for path in (folder, *folder.rglob("*")):
        os.chown(path, 0, 0)
        path.chmod(0o755 if path.is_dir() else 0o644)
    yield folder / "dcmotor" / "dcmotor.toml"
    shutil.rmtree(folder, ignore_errors=True)


def test_a_sweep_into_roots_folder_says_so_in_one_line(second_user, open_dir: Path, roots_dcmotor: Path,
                                                       rtloop_env) -> None:
    out = open_dir / "sweep-sudo"  # what a sweep under sudo left: root's
    (out / "0").mkdir(parents=True)
    (out / "sweep.csv").write_text("pi.kp\n")
    app_file = roots_dcmotor
    code = ("import sys; from rtloop.cli.main import main; "
            f"sys.exit(main(['sweep', {str(app_file)!r}, '--param', 'pi.kp=0.05,0.1', '--duration', '0.1', "
            f"'--out', {str(out)!r}, '--force', '--processes', '1']))")
    done = _as(second_user, code, rtloop_env)
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert f"--out {out}" in done.stderr and "permission denied" in done.stderr.lower(), done.stderr
    assert (out / "sweep.csv").read_text() == "pi.kp\n"


# --- serial devices: a link or a pty another user planted (B7) --------------------------------
@pytest.fixture
def pty_path() -> Iterator[str]:
    main, follower = os.openpty()
    yield os.ttyname(follower)
    os.close(main)
    os.close(follower)


def _serial(port: Path | str):
    from rtloop.io.serial import SerialDevice

    return SerialDevice("motor", port=str(port), baudrate=115200, timeout_ms=5.0, commands=["v"], readings=["w"])


@needs_root
def test_a_serial_link_another_user_planted_is_refused(open_dir: Path, pty_path: str) -> None:
    from rtloop.errors import DeviceError

    link = open_dir / "motor.tty"  # /tmp-like: anyone may plant a name there first
    link.symlink_to(pty_path)
    _serial(link).check()  # root's own link to root's pty
    os.chown(link, NOBODY_UID, NOBODY_UID, follow_symlinks=False)
    with pytest.raises(DeviceError, match=f"{link} is a symbolic link owned by uid {NOBODY_UID}"):
        _serial(link).check()


@needs_root
def test_a_serial_device_node_of_another_user_is_refused(open_dir: Path, pty_path: str) -> None:
    from rtloop.errors import DeviceError

    link = open_dir / "motor.tty"
    link.symlink_to(pty_path)
    os.chown(pty_path, NOBODY_UID, -1)  # their pty: they read every command and answer as the motor
    for port in (pty_path, link):
        with pytest.raises(DeviceError, match=f"{pty_path} is owned by uid {NOBODY_UID}"):
            _serial(port).check()


# --- model files: an FMU or 20-sim export is code too ------------------------------------------
def _model_app(folder: Path, name: str, model: str) -> Path:
    path = folder / f"{name}.toml"
    path.write_text(f'name = "{name}"\n[tasks.t]\nmodel = "{model}"\nperiod_ns = 1_000_000\n')
    return path


@needs_root
@pytest.mark.parametrize("what", ["fmu file", "20-sim file", "folder"])
def test_a_model_another_user_could_change_is_refused(tmp_path: Path, what: str) -> None:
    folder = tmp_path / "app"
    (folder / "models" / "Plant").mkdir(parents=True)
    fmu = folder / "plant.fmu"
    fmu.write_bytes(b"PK\x05\x06" + bytes(18))  # an empty zip: never opened when refused
    source = folder / "models" / "Plant" / "Plant.c"
    source.write_text("/* a 20-sim export */\n")
    if what == "fmu file":
        os.chown(fmu, NOBODY_UID, NOBODY_UID)
        spec, culprit = "fmu:plant.fmu", fmu
    elif what == "20-sim file":
        os.chown(source, NOBODY_UID, NOBODY_UID)
        spec, culprit = "20sim:models/Plant", source
    else:
        os.chown(folder, NOBODY_UID, NOBODY_UID)
        spec, culprit = "fmu:plant.fmu", folder
    with pytest.raises(AppFileError, match=f"tasks.t.model: {culprit} is owned by uid {NOBODY_UID}"):
        load_app(_model_app(folder, f"model{os.getpid()}", spec))


def _grant_write_by_acl(path: Path, uid: int) -> None:
    """An access ACL (as setfacl -m u:UID:rwx writes it) letting ``uid`` write; group bits become its mask."""
    import struct

    undefined = 0xFFFFFFFF
    entries = [(0x01, 7, undefined), (0x02, 7, uid), (0x04, 5, undefined), (0x10, 7, undefined), (0x20, 5, undefined)]
    acl = struct.pack("<I", 2) + b"".join(struct.pack("<HHI", *entry) for entry in entries)
    try:
        os.setxattr(path, "system.posix_acl_access", acl)
    except OSError as error:
        pytest.skip(f"no POSIX ACLs on this file system ({error.strerror})")


@needs_root
def test_a_folder_another_user_may_write_through_an_acl_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "app"
    folder.mkdir()
    module = f"acl_{secrets.token_hex(3)}"
    (folder / f"{module}.py").write_text(PLANTED_PYC_MODULE)
    app_file = _app_toml(folder, f"acl{os.getpid()}", f"{module}:Here")
    _grant_write_by_acl(folder, NOBODY_UID)
    assert stat.S_IMODE(folder.stat().st_mode) == 0o775 and folder.stat().st_gid == 0  # group root: looks fine
    with pytest.raises(AppFileError, match=f"{folder} is writable through an ACL by uid {NOBODY_UID}"):
        load_app(app_file)


@needs_root
def test_a_cached_20sim_library_another_user_could_have_written_is_refused(tmp_path: Path) -> None:
    import shutil

    from rtloop.models.base import ModelError
    from rtloop.models.twentysim import build_library, inspect

    plant = Path(__file__).parents[1] / "examples" / "jiwy" / "models" / "Plant"
    if shutil.which("gcc") is None and shutil.which("cc") is None:
        pytest.skip("no C compiler to build the 20-sim model")
    info = inspect(plant)
    cache = tmp_path / "cache"
    library = build_library(info, cache_dir=cache)
    assert build_library(info, cache_dir=cache) == library  # root's own: taken from the cache
    os.chown(library, NOBODY_UID, NOBODY_UID)  # one they replaced, with the name the hash gives
    with pytest.raises(ModelError, match=f"{library} is owned by uid {NOBODY_UID}"):
        build_library(info, cache_dir=cache)
    os.chown(library, 0, 0)
    cache.chmod(0o777)
    with pytest.raises(ModelError, match=f"{cache} is writable by every user"):
        build_library(info, cache_dir=cache)


@needs_root
def test_a_cache_writable_by_a_private_group_is_fine(tmp_path: Path) -> None:
    from rtloop.models.twentysim.build import _foreign_cache

    library = tmp_path / "cache" / "m.so"  # umask 002 (user private groups) makes folders 775
    library.parent.mkdir()
    library.write_bytes(b"")
    for path in (library, library.parent):
        path.chmod(0o775)
    assert _foreign_cache(library) is None  # group root: only root in it
    os.chown(library.parent, 0, NOBODY_UID)
    assert "writable by group" in _foreign_cache(library)
