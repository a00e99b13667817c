"""The report builder: trust grades from closed forms, and a self-contained HTML page."""

import base64
import math
from html.parser import HTMLParser

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from torchconn.plotting import render_png  # noqa: E402
from torchconn.report import Report, trust  # noqa: E402


def test_trust_grades_the_band_against_the_estimate():
    value = np.array([3.0, -4.0])  # RMS sqrt(12.5)
    for se, word in ((0.1, "well"), (0.3, "roughly"), (1.0, "poorly")):
        got, ratio = trust(value, np.full(2, se))
        assert got == word
        assert ratio == pytest.approx(1.96 * se / math.sqrt(12.5))
    assert trust(value, [np.nan, np.nan])[0] == "not estimated"
    assert trust([0.0, 0.0], [1.0, 1.0]) == ("poorly", math.inf)
    # NaN entries are skipped, not propagated
    assert trust([3.0, np.nan], [0.01, 5.0])[0] == "well"


class _Page(HTMLParser):
    def __init__(self):
        super().__init__()
        self.images, self.links, self.scripts, self.captions = [], [], 0, 0

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "img":
            self.images.append(attrs["src"])
        if tag in ("a", "link") and "href" in attrs:
            self.links.append(attrs["href"])
        self.scripts += tag == "script"
        self.captions += tag == "figcaption"


def test_the_page_embeds_its_figures_and_links_nowhere(tmp_path):
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1], label="line")
    report = Report("torchconn-fit: <fish>.csv", "One trial.")
    report.section("What was fitted", ["5 links", "gait 2.0 Hz"], note="small print")
    report.table("Held-out R²", ["component", "model"], [["v_x", 0.5], ["omega", 0.9]])
    report.figure(render_png(fig)[0], "A line & what good looks like.")
    with pytest.raises(TypeError, match="png must be the bytes of a PNG"):
        report.figure(fig, "a Figure, not rendered")
    path = report.write(tmp_path / "report.html")
    page = path.read_text()
    parser = _Page()
    parser.feed(page)
    assert parser.links == [] and parser.scripts == 0 and parser.captions == 1
    (src,) = parser.images
    assert src.startswith("data:image/png;base64,")
    assert base64.b64decode(src.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
    assert "&lt;fish&gt;" in page and "A line &amp; what good" in page  # escaped
    text = report.text()
    assert text[0] == "torchconn-fit: <fish>.csv" and "  - gait 2.0 Hz" in text
    assert any(line.split() == ["omega", "0.9"] for line in text)
    assert report.n_figures == 1
