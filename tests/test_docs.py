"""The docs say what the product does: their snippets load, their claims match the code."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

from rtloop.app.appfile import load_app
from rtloop.toolbox import doctor

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"


def toml_snippets(path: Path) -> list[str]:
    return re.findall(r"```toml\n(.*?)```", path.read_text(), flags=re.S)


def test_the_devices_pages_first_snippet_loads_beside_the_example_it_quotes(tmp_path: Path) -> None:
    snippet = toml_snippets(DOCS / "devices.md")[0]
    assert "examples/dcmotor_serial" in snippet
    shutil.copytree(REPO / "examples" / "dcmotor", tmp_path / "dcmotor")  # serial_motor imports its PI from there
    folder = tmp_path / "dcmotor_serial"
    folder.mkdir()
    shutil.copy(REPO / "examples" / "dcmotor_serial" / "serial_motor.py", folder)
    (folder / "app.toml").write_text('name = "docs_devices"\n' + snippet)
    app = load_app(folder / "app.toml")  # every name it gives exists: runnable, twin, limits, connections
    assert list(app.devices) == ["motor"] and list(app.tasks) == ["pi"]


def test_the_docs_say_what_rtloop_does_with_cpu_dma_latency() -> None:
    assert doctor.RTLOOP_HOLDS_CPU_DMA_LATENCY
    for page in (*DOCS.glob("*.md"), REPO / "README.md"):
        text = " ".join(page.read_text().split())
        assert "does not yet hold `/dev/cpu_dma_latency`" not in text, page.name
    comment = (REPO / "src" / "rtloop" / "toolbox" / "doctor.py").read_text()
    assert "It does not yet" not in comment


def test_the_readme_says_where_the_rtloop_command_is_before_using_it_bare() -> None:
    text = (REPO / "README.md").read_text()
    first_bare = re.search(r"(^|`)rtloop (run|simulate|report|port|replay|sweep|top|doctor) ", text, flags=re.M)
    assert first_bare is not None
    said = text.find(".venv/bin/activate")
    assert 0 <= said < first_bare.start(), "the README uses `rtloop ...` before saying where the command lives"


def test_security_page_allows_what_first_app_shows_sibling_modules() -> None:
    security = " ".join((DOCS / "security.md").read_text().split())
    assert "No other file in the folder can be imported" not in security
    assert "may import other modules from the same folder" in security
    assert "from motor import PiSpeed" in (DOCS / "first-app.md").read_text()
