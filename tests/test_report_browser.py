"""The commands' HTML reports open in a real browser (Debian's headless Chromium): every
figure decodes and shows, and no link is broken. Slow; skipped where Chromium is not installed
(``apt-get install chromium``)."""

import re
import shutil
import subprocess

import numpy as np
import pytest

from torchconn import NLinkSwimmer, observe, simulate, write_csv
from torchconn.improve.loop import circle_gait

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (apt-get install "
                                 "chromium)")]

#: appended to a copy of a report: after load, record how many images decoded with a size,
#: how many did not, and the in-page links whose target is missing
_PROBE = """<script>
window.addEventListener('load', () => {
  const imgs = [...document.images];
  const shown = imgs.filter(i => i.complete && i.naturalWidth > 0 && i.offsetWidth > 0);
  const broken = [...document.querySelectorAll('a[href]')].map(a => a.getAttribute('href'))
    .filter(h => !(h.startsWith('#') && document.getElementById(h.slice(1))));
  document.body.setAttribute('data-probe',
    `${imgs.length} ${shown.length} ${broken.length}`);
});
</script>"""


def _open(report, tmp_path) -> tuple[int, int, int]:
    """(images, images shown, broken links) of ``report`` as Chromium renders it."""
    probe = tmp_path / f"probe-{report.parent.name}.html"
    probe.write_text(report.read_text().replace("</body>", _PROBE + "</body>"))
    dom = subprocess.run(
        [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
         "--no-first-run", "--disable-background-networking", "--disable-component-update",
         "--disable-sync", f"--user-data-dir={tmp_path / 'chromium'}",
         "--virtual-time-budget=5000", "--dump-dom", probe.as_uri()],
        capture_output=True, text=True, timeout=120, check=True).stdout
    found = re.search(r'data-probe="(\d+) (\d+) (\d+)"', dom)
    assert found, dom[-2000:]
    return tuple(int(x) for x in found.groups())


def _recording(tmp_path, name="rec.csv", n_cycles=10):
    seeds = np.arange(2)
    traj = observe(simulate(NLinkSwimmer(3), circle_gait(2, 0.8), eta=0.025,
                            n_cycles=n_cycles, seeds=seeds), 0.002, seeds=seeds)
    return write_csv(traj, tmp_path / name)


def test_fit_report_renders_every_figure(tmp_path):
    from torchconn.fit import main

    out = tmp_path / "fit"
    assert main([str(_recording(tmp_path)), "--out", str(out), "--quiet"]) == 0
    images, shown, broken = _open(out / "report.html", tmp_path)
    pngs = {p.name for p in out.glob("*.png")}
    assert images == len(pngs) >= 3 and shown == images and broken == 0
    page = (out / "report.html").read_text()
    for heading in ("What was fitted", "How well it predicts cycles it did not see",
                    "Which parts of the model can be trusted", "What to do next"):
        assert heading in page


def test_discrepancy_report_renders_every_figure(tmp_path):
    from torchconn.discrepancy.__main__ import main

    out = tmp_path / "disc"
    assert main([str(_recording(tmp_path, n_cycles=12)), "--links", "3", "--frame",
                 "center", "--out", str(out), "--quiet"]) == 0
    images, shown, broken = _open(out / "report.html", tmp_path)
    assert images == len(list(out.glob("*.png"))) >= 1 and shown == images and broken == 0
    assert "Verdict" in (out / "report.html").read_text()


def test_improve_report_renders(tmp_path):
    from torchconn.improve.__main__ import main

    out = tmp_path / "next"
    assert main(["propose", str(_recording(tmp_path)), "--out", str(out), "--quiet"]) == 0
    images, shown, broken = _open(out / "report.html", tmp_path)
    assert (images, shown, broken) == (0, 0, 0)
    page = (out / "report.html").read_text()
    assert "The gait you recorded" in page and "the model predicts" in page
