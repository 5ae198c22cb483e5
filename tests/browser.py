"""Open a page in headless Chromium (Debian's `chromium` package) and return the DOM after its images loaded or
failed: the report's images mark a failure with `data-broken` (report_html.page), so a test sees one that does not
load. Skips the calling test when no Chromium is installed (.ci/run installs it)."""
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

# without the background-networking flags Chromium's connections are refused by a closed network, many at a time
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync")


def chromium() -> str:
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        pytest.skip("no chromium (Debian's package: apt-get install chromium; .ci/run installs it)")
    return path


def _fresh(profile: Path) -> Path:
    """A new profile directory per run: a second Chromium on one profile hands its page to the first."""
    profile.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(dir=profile))


def dump_dom(page: Path, profile: Path) -> str:
    profile = _fresh(profile)
    out = subprocess.run([chromium(), *FLAGS, f"--user-data-dir={profile}", "--virtual-time-budget=10000",
                          "--dump-dom", page.resolve().as_uri()], capture_output=True, text=True, timeout=180,
                         env={**os.environ, "HOME": str(profile)})
    assert out.returncode == 0 and "</html>" in out.stdout, out.stderr[-2000:]
    return out.stdout


def screenshot(page: Path, png: Path, profile: Path, size=(1280, 900)) -> None:
    profile = _fresh(profile)
    subprocess.run([chromium(), *FLAGS, f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
                    "--hide-scrollbars", f"--screenshot={png.resolve()}", page.resolve().as_uri()],
                   capture_output=True, timeout=180, check=True, env={**os.environ, "HOME": str(profile)})


def images(dom: str) -> list[str]:
    return re.findall(r"<img\b[^>]*>", dom)


def answers_first(dom: str) -> None:
    """The verdict, then the ranking as the page's first table, and every image loaded."""
    verdict, ranking = dom.find('id="verdict"'), dom.find('<table id="ranking"')
    assert 0 <= verdict < ranking, "the verdict comes first, then the ranking"
    assert dom.find("<table") == ranking, "the ranking is the first table"
    broken = [i for i in images(dom) if 'data-loaded="1"' not in i]  # set by its onload (report_html.page)
    assert not broken, f"images that did not load: {broken}"
