"""The study's HTML report: tables, numbers, escaping, images, atomic files, a real browser."""

from __future__ import annotations

import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import pytest
from PIL import Image

from rayaccel.cli import main
from rayaccel.study.config import parse_config
from rayaccel.study.report import write_report
from rayaccel.study.results import ResultsFile, ResultsFormatError
from rayaccel.study.sweep import sweep

#: Debian's chromium, found on PATH (``.ci/run`` installs it).
CHROMIUM = shutil.which("chromium")
EVIL = "<script>alert('boom')</script>"
SCENES = ("cornell-box", "teapot")
SYSTEMS = {  # traversal -> (builder, base Mrays/s on one thread)
    "bvh2.stack": ("bvh2.binned_sah", 10.0),
    "bvh2.wide": ("bvh2.binned_sah", 12.3456),
    "kdtree.stack": ("kdtree.sah", 7.0),
    "grid.dda": ("grid.uniform", 3.0),
}
BUILDS = {"bvh2.binned_sah": (1.5, 1184), "kdtree.sah": (4.25, 2192), "grid.uniform": (0.75, 5000)}
HEADER = {
    "rayaccel": "0.1.0",
    "config": {"scenes": list(SCENES), "threads": [1, 2], "peers": ["embree"],
               "rays": {"kinds": ["primary", "diffuse", "shadow"]}},
    "environment": {"cpu_model": "Test CPU 9000", "cpu_count": 2, "numba_version": "0.0.test"},
}  # fmt: skip


def key(kind, scene, builder, traversal, rayset, threads):
    return f"{kind}|{scene}|{builder}|{traversal or '-'}|{rayset or '-'}|t{threads}|abc"


def ident(kind, scene, builder, traversal, rayset, threads):
    return {"key": key(kind, scene, builder, traversal, rayset, threads), "kind": kind,
            "scene": scene, "builder": builder, "traversal": traversal, "rayset": rayset,
            "threads": threads, "attempts": 1, "seconds": 0.1}  # fmt: skip


def mrays(scene, traversal, rayset, threads):
    scale = (1.0 if scene == "cornell-box" else 0.5) * threads * (1.5 if rayset == "shadow" else 1)
    return round(SYSTEMS[traversal][1] * scale, 4)


def write_results(path, scenes=SCENES):
    """A synthetic sweep: two scenes, four systems, primary and shadow rays, 1 and 2 threads."""
    out = ResultsFile(path, HEADER)
    # An early record of a cell that a later one replaces (the last record of a key wins)
    early = ident("timing", scenes[0], "bvh2.binned_sah", "bvh2.wide", "primary", 1)
    out.append({**early, "status": "ok", "mrays_median": 99.99, "peers": {}})
    for scene in scenes:
        factor = 1 if scene == scenes[0] else 30
        for builder, (ms, size) in BUILDS.items():
            for threads in (1, 2):
                out.append({**ident("build", scene, builder, None, None, threads), "status": "ok",
                            "build_ms_median": ms * factor / threads, "structure":
                            builder.split(".")[0], "bytes": size * factor})  # fmt: skip
        for traversal, (builder, _) in SYSTEMS.items():
            for rayset in ("primary", "shadow"):
                grid = builder.startswith("grid")
                bad = 3 if (grid and rayset == "shadow" and scene == scenes[1]) else 0
                out.append({**ident("counters", scene, builder, traversal, rayset, 1),
                            "status": "ok", "n_rays": 192, "hit_rate": 0.75,
                            "nodes_per_ray": 0.0 if grid else 9.9043,
                            "prims_per_ray": 3.2122, "nodes_p95": 13.0,
                            "counters_mean": {"cells": 42.5 if grid else 0.0},
                            "bytes_per_ray": 725.3906, "validated": 100,
                            "mismatches": bad})  # fmt: skip
                for threads in (1, 2):
                    record = ident("timing", scene, builder, traversal, rayset, threads)
                    if (scene, traversal, rayset, threads) == (scenes[1], "kdtree.stack",
                                                                "primary", 2):  # fmt: skip
                        out.append({**record, "status": "failed", "attempts": 3,
                                    "error": f"RuntimeError: {EVIL}",
                                    "traceback": "Traceback: ..."})  # fmt: skip
                        continue
                    peers = {}
                    notes = ["embree: runs on part of the rays only"] if grid else []
                    if not grid:
                        offset = {"bvh2.stack": 0.0, "bvh2.wide": 2.0, "kdtree.stack": 4.0}
                        value = (20.0 + offset[traversal]) * (1.0 if scene == scenes[0] else 0.5)
                        peers = {"embree": {"mrays_median": value, "ratio": 1.0}}
                    out.append({**record, "status": "ok", "n_rays": 192, "repeats": 3,
                                "ms_median": 1.0, "ms_best": 0.9,
                                "mrays_median": mrays(scene, traversal, rayset, threads),
                                "mrays_best": 1.0, "peers": peers, "notes": notes})  # fmt: skip
    return path


class Page(HTMLParser):
    """The parts of the page the tests read: tables (caption, cells and classes), images."""

    def __init__(self, html):
        super().__init__()
        self.lang = None
        self.title = ""
        self.tables = []
        self.images = []
        self.headings = []
        self._text = None
        self._css = ""
        self.feed(html)

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "html":
            self.lang = a.get("lang")
        elif tag == "table":
            self.tables.append({"caption": None, "rows": []})
        elif tag == "tr":
            self.tables[-1]["rows"].append([])
        elif tag == "img":
            self.images.append(a)
        if tag in ("td", "th", "caption", "title", "h2"):
            self._text, self._css = [], a.get("class") or ""

    def handle_data(self, data):
        if self._text is not None:
            self._text.append(data)

    def handle_endtag(self, tag):
        if tag not in ("td", "th", "caption", "title", "h2") or self._text is None:
            return
        text = " ".join("".join(self._text).split())
        self._text = None
        if tag == "caption":
            self.tables[-1]["caption"] = text
        elif tag == "title":
            self.title = text
        elif tag == "h2":
            self.headings.append(text)
        else:
            self.tables[-1]["rows"][-1].append((text, self._css))

    def table(self, title):
        found = [t for t in self.tables if t["caption"] and t["caption"].endswith(title)]
        assert len(found) == 1, (title, [t["caption"] for t in self.tables])
        return found[0]

    def cell(self, title, row, column):
        """Return ``(text, css)`` of the cell in the row starting ``row``, under ``column``."""
        rows = self.table(title)["rows"]
        index = [h for h, _ in rows[0]].index(column)
        matches = [r for r in rows[1:] if r[0][0] == row]
        assert len(matches) == 1, (row, rows)
        return matches[0][index]


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    folder = tmp_path_factory.mktemp("report")
    results = write_results(folder / "results.jsonl")
    index = write_report(results, folder / "out")
    return index, index.read_text(), Page(index.read_text())


def test_every_table_is_present_with_its_caption(report):
    _, _, page = report
    titles = [f"Mrays/s by scene × structure: {s} rays, {t}"
              for s in ("primary", "shadow") for t in ("1 thread", "2 threads")]  # fmt: skip
    titles += ["Build time by scene × builder: median ms, 1 thread",
               "Build time by scene × builder: median ms, 2 threads",
               "Structure size by scene × builder", "Traversal cost per ray: primary rays",
               "Traversal cost per ray: shadow rays", "Failed cells", "Machine and versions",
               "Sweep configuration"]  # fmt: skip
    for title in titles:
        page.table(title)
    assert len(page.tables) == len(titles)
    assert [t["caption"].split(".")[0] for t in page.tables] == [
        f"Table {k}" for k in range(1, len(titles) + 1)
    ]
    # A ray set absent from the results (diffuse) gets no table
    assert not any("diffuse" in t["caption"] for t in page.tables)
    assert page.headings[:5] == ["Ray throughput", "Build time and size", "Traversal cost",
                                 "Failed cells", "Machine and versions"]  # fmt: skip


def test_throughput_numbers_peers_averages_and_failures(report):
    _, html, page = report
    title = "Mrays/s by scene × structure: primary rays, 1 thread"
    assert page.cell(title, "bvh2.binned_sah + bvh2.wide", "cornell-box") == ("12.35", "num")
    assert page.cell(title, "bvh2.binned_sah + bvh2.wide", "teapot")[0] == "6.17"
    assert page.cell(title, "bvh2.binned_sah + bvh2.wide", "average across scenes")[0] == "9.26"
    # The peer's row: the median of its Mrays/s over the scene's cells (20, 22, 24 -> 22)
    assert page.cell(title, "embree (peer)", "cornell-box") == ("22.00", "num best peer")
    assert page.cell(title, "embree (peer)", "teapot") == ("11.00", "num best peer")
    # The fastest of each scene is in bold
    title = "Mrays/s by scene × structure: shadow rays, 2 threads"
    assert page.cell(title, "bvh2.binned_sah + bvh2.wide", "cornell-box") == ("37.04", "num best")
    assert page.cell(title, "embree (peer)", "cornell-box") == ("22.00", "num peer")
    # The last record of a key wins
    assert "99.99" not in html
    title = "Mrays/s by scene × structure: primary rays, 2 threads"
    assert page.cell(title, "kdtree.sah + kdtree.stack", "teapot") == ("failed", "num bad")
    assert page.cell(title, "kdtree.sah + kdtree.stack", "average across scenes")[0] == "14.00*"
    assert page.cell(title, "embree (peer)", "teapot")[0] == "10.50"  # median of 10 and 11
    assert "embree: runs on part of the rays only" in html


def test_build_and_counter_tables(report):
    _, _, page = report
    assert page.cell("median ms, 2 threads", "kdtree.sah", "teapot")[0] == "63.75"
    assert page.cell("Structure size by scene × builder", "bvh2.binned_sah", "cornell-box")[0] \
        == "1.2 KiB"  # fmt: skip
    rows = page.table("Traversal cost per ray: shadow rays")["rows"]
    header = [h for h, _ in rows[0]]
    by_system = {(r[0][0], r[1][0]): dict(zip(header, r, strict=True)) for r in rows[1:]}
    stack = by_system[("cornell-box", "bvh2.binned_sah + bvh2.stack")]
    assert stack["nodes/ray (grids: cells)"][0] == "9.90"
    assert stack["prim tests/ray"][0] == "3.21"
    assert stack["bytes/ray"][0] == "725"
    assert stack["hit rate"][0] == "75.0%"
    assert stack["mismatches/validated"] == ("0/100", "num")
    grid = by_system[("teapot", "grid.uniform + grid.dda")]
    assert grid["nodes/ray (grids: cells)"][0] == "42.50"
    assert grid["mismatches/validated"] == ("3/100", "num bad")


def test_failed_cells_machine_and_config(report):
    _, _, page = report
    rows = page.table("Failed cells")["rows"]
    assert len(rows) == 2
    assert rows[1][0][0] == key("timing", "teapot", "kdtree.sah", "kdtree.stack", "primary", 2)
    assert rows[1][2][0].startswith(f"RuntimeError: {EVIL}")
    assert page.cell("Machine and versions", "cpu_model", "value")[0] == "Test CPU 9000"
    assert page.cell("Machine and versions", "rayaccel", "value")[0] == "0.1.0"
    assert page.cell("Sweep configuration", "threads", "value")[0] == "[1, 2]"


def test_text_is_escaped(tmp_path):
    results = write_results(tmp_path / "evil.jsonl", scenes=("cornell-box", EVIL))
    html = write_report(results, tmp_path / "out").read_text()
    assert "<script" not in html.lower()
    assert "&lt;script&gt;alert(&#39;boom&#39;)&lt;/script&gt;" in html
    page = Page(html)
    assert EVIL in [h for h, _ in page.table("Structure size by scene × builder")["rows"][0]]


def test_page_structure_and_images(report):
    index, html, page = report
    assert page.lang == "en"
    assert page.title
    assert html.lstrip().startswith("<!DOCTYPE html>")
    assert all(t["caption"] for t in page.tables)
    assert len(page.images) == 2 * 3 + 1  # bvh2, kdtree, grid x primary, shadow; traffic
    for img in page.images:
        assert img["alt"]
        path = index.parent / img["src"]
        assert Path(img["src"]).name == img["src"]  # relative, beside the page
        with Image.open(path) as png:
            assert png.format == "PNG"
            assert png.size == (int(img["width"]), int(img["height"]))
    # Nothing is fetched over the network: no URL at all, no script
    assert not re.search(r"https?://", html)
    assert "<script" not in html


def test_files_are_written_atomically_and_rewritten(report):
    index, _, _ = report
    names = sorted(p.name for p in index.parent.iterdir())
    assert not [n for n in names if n.startswith(".") or n.endswith(".tmp")]
    assert write_report(index.parent.parent / "results.jsonl", index.parent) == index
    assert sorted(p.name for p in index.parent.iterdir()) == names


def test_empty_sections_are_left_out(tmp_path):
    out = ResultsFile(tmp_path / "builds.jsonl", HEADER)
    out.append({**ident("build", "cornell-box", "bvh2.binned_sah", None, None, 1), "status": "ok",
                "build_ms_median": 1.5, "bytes": 1184})  # fmt: skip
    page = Page(write_report(out.path, tmp_path / "out").read_text())
    assert page.headings == ["Build time and size", "Machine and versions"]
    assert page.images == []


def test_another_format_is_refused(tmp_path):
    path = tmp_path / "other.jsonl"
    path.write_text('{"record": "header", "format": "other/9"}\n')
    with pytest.raises(ResultsFormatError):
        write_report(path, tmp_path / "out")
    assert not (tmp_path / "out" / "index.html").exists()


def test_cli_report(tmp_path, capsys):
    results = write_results(tmp_path / "results.jsonl")
    assert main(["report", str(results), "-o", str(tmp_path / "out")]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "out" / "index.html")


WRAPPER_SCRIPT = """<script>
window.addEventListener("load", function () {
  var images = Array.prototype.slice.call(document.images);
  document.body.setAttribute("data-images", images.map(function (img) {
    return (img.complete && img.naturalWidth > 0 ? "ok:" : "broken:") + img.getAttribute("src");
  }).join(" "));
  document.body.setAttribute("data-tables", document.querySelectorAll("table > caption").length);
});
</script>"""


def chromium_dom(page, user_data):
    if CHROMIUM is None:
        pytest.fail("chromium is not on PATH: install Debian's chromium (apt-get install chromium)")
    command = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
               "--no-first-run", "--disable-background-networking", "--disable-component-update",
               "--disable-sync", f"--user-data-dir={user_data}", "--virtual-time-budget=5000",
               "--dump-dom", page.as_uri()]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def test_chromium_renders_every_table_and_image(report, tmp_path):
    index, html, page = report
    # A copy of the report, so the wrapper page (with its script) stays out of the report
    copy = tmp_path / "site"
    shutil.copytree(index.parent, copy)
    dom = chromium_dom(copy / "index.html", tmp_path / "profile")
    assert len(re.findall(r"<caption>", dom)) == len(page.tables)
    for table in page.tables:
        assert table["caption"] in dom
    wrapper = copy / "wrapper.html"
    wrapper.write_text(html.replace("</body>", WRAPPER_SCRIPT + "</body>"))
    dom = chromium_dom(wrapper, tmp_path / "profile")
    found = re.search(r'<body[^>]*data-images="([^"]*)"', dom)
    assert found, dom[:2000]
    states = found.group(1).split()
    assert len(states) == len(page.images)
    assert all(state.startswith("ok:") for state in states), states
    assert re.search(rf'data-tables="{len(page.tables)}"', dom)


TINY = """\
scenes = ["cornell-box"]
builders = ["bvh2.binned_sah"]
traversals = ["bvh2.stack"]
threads = [1]
repeats = 1
build_repeats = 1
validate = 20
peers = []

[rays]
kinds = ["primary", "shadow"]
width = 16
height = 12
"""


def test_report_of_a_real_sweep_with_heatmaps(tmp_path):
    results = tmp_path / "results.jsonl"
    summary = sweep(parse_config(TINY), results)
    assert summary.failed == 0
    index = write_report(results, tmp_path / "out", heatmaps=True)
    page = Page(index.read_text())
    for title in ("primary rays, 1 thread", "shadow rays, 1 thread",
                  "median ms, 1 thread", "Traversal cost per ray: primary rays"):  # fmt: skip
        page.table(title)
    assert "Heatmaps" in page.headings
    heat = [img for img in page.images if img["src"].startswith("heat-")]
    assert [img["alt"] for img in heat] == [
        "legend: nodes: nodes visited per ray (log scale)",
        "nodes per primary ray, cornell-box, bvh2.binned_sah + bvh2.stack",
    ]
    with Image.open(index.parent / heat[1]["src"]) as png:
        assert png.size == (160, 120) == (int(heat[1]["width"]), int(heat[1]["height"]))
    for img in page.images:
        with Image.open(index.parent / img["src"]) as png:
            assert png.format == "PNG"
