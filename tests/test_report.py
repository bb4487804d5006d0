"""``glaciar report RUN --html``: one self-contained page, read back and opened in Chromium.

The run is the session's ``deep_corner_run`` (one field whose corner is 1.3 mag deeper),
copied, reported before a fit, fitted (logistic step), and reported again.  The page is
parsed back: its numbers must equal those of the run's summary tables, the selection-
function file and ``fit/summary.json``; every image must decode; nothing may point outside
the page.  Headless Chromium (Debian package ``chromium``; ``.ci/run`` installs it) then
loads the page over the DevTools protocol (a pipe, no network port) in a 1280 px wide
window and must report no console error and every figure decoded and laid out at its own
(readable) size.  Without Chromium that test skips.  The figures' contents (legends, log
axes, empty cells) are checked on the Figure objects (below).
"""
import ast
import base64
import html
import io
import json
import math
import os
import re
import select
import shutil
import subprocess
import sys
import tempfile
import textwrap
import time
import warnings
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from astropy.io import fits
from astropy.table import Table

import glaciar
from glaciar import constants as C, plots, report
from glaciar.cli import main
from glaciar.report import ADAPTIVE_ROUNDS_NAME, REPORT_NAME, load_report_data

from figure_cases import SIM_M, SIM_Z, legend_labels, report_figures

#: every figure a fitted single-fit report shows (ids of <figure> elements)
FITTED_FIGURES = ("fig-status", "fig-completeness-all", "fig-selection-all", "fig-p-all",
                  "fig-ppc-all", "fig-area-by-depth", "fig-depth-all", "fig-veff-all")
SECTIONS = ("summary", "configuration", "statistics", "status", "curves", "ppc", "depth", "adaptive",
            "selection-function")


class _Page(HTMLParser):
    """Tables (by id: column names and rows of (exact value, shown text)), images, sections."""

    def __init__(self, text):
        super().__init__()
        self.tables, self.images, self.ids, self.attrs_all = {}, [], [], []
        self._table = self._row = self._cell = None
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.attrs_all.append((tag, a))
        if "id" in a:
            self.ids.append(a["id"])
        if tag == "table":
            self._table = {"columns": [], "rows": [], "keys": []}
            self.tables[a.get("id")] = self._table
        elif tag == "tr" and self._table is not None:
            self._row = []
        elif tag == "th" and self._table is not None:
            if "data-column" in a:
                self._table["columns"].append(a["data-column"])
            if "data-key" in a:
                self._table["keys"].append(a["data-key"])
        elif tag == "td" and self._row is not None:
            self._cell = [a.get("data-value"), ""]
        elif tag == "img":
            self.images.append(a)

    def handle_data(self, data):
        if self._cell is not None:
            self._cell[1] += data

    def handle_endtag(self, tag):
        if tag == "td" and self._cell is not None:
            self._row.append(tuple(self._cell))
            self._cell = None
        elif tag == "tr" and self._row is not None:
            if self._row:
                self._table["rows"].append(self._row)
            self._row = None
        elif tag == "table":
            self._table = None

    def column(self, table_id, name):
        t = self.tables[table_id]
        j = t["columns"].index(name)
        return [r[j] for r in t["rows"]]

    def kv(self, table_id):
        t = self.tables[table_id]
        return {k: r[0] for k, r in zip(t["keys"], t["rows"])}


def _exact(cells):
    """The exact values of table cells as floats (ints, 'nan', 'true'/'false' included)."""
    return np.array([{"true": 1.0, "false": 0.0}.get(v, None) if v in ("true", "false")
                     else float(v) for v, _ in cells])


@pytest.fixture(scope="module")
def reported(deep_corner_run, tmp_path_factory):
    """(run dir, page before the fit, page after the fit).

    The fit is capped at 400 steps per chain (~9 s CPU instead of ~26 s): the page shows
    what the files hold, converged or not.
    """
    from glaciar.inference.sampling import SamplerSettings
    from glaciar.pipeline import run_fit

    _, src = deep_corner_run
    run = tmp_path_factory.mktemp("html_report") / "run"
    shutil.copytree(src, run, ignore=shutil.ignore_patterns(
        "fit", C.SELECTION_FUNCTION_NAME, C.SUMMARY_DIRNAME, REPORT_NAME, C.LOCK_NAME))
    assert main(["report", str(run), "--html"]) == 0
    before = (run / REPORT_NAME).read_text(encoding="utf-8")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run_fit(run, model="logistic", max_draws=400, sampler=SamplerSettings(max_steps=400))
    assert main(["report", str(run), "--html"]) == 0
    return run, before, (run / REPORT_NAME).read_text(encoding="utf-8")


def test_page_has_every_section_and_figure(reported):
    run, before, after = reported
    page = _Page(after)
    for sid in SECTIONS:
        assert sid in page.ids, sid
    for fid in FITTED_FIGURES:
        assert fid in page.ids, fid
    assert len(page.images) == len(FITTED_FIGURES)
    # The adaptive loop does not exist yet: the section says so.
    assert "adaptive-none" in page.ids
    assert re.search(r'id="adaptive-none">none\b', after)


def test_numbers_equal_the_summary_tables(reported):
    run, _, html_text = reported
    page = _Page(html_text)
    for name in ("all", "corner"):
        t = Table.read(run / C.SUMMARY_DIRNAME / f"summary_{name}.ecsv").to_pandas()
        assert page.tables[f"summary-{name}"]["columns"][:2] == ["z", "mag"]
        for col in page.tables[f"summary-{name}"]["columns"]:
            got = _exact(page.column(f"summary-{name}", col))
            np.testing.assert_array_equal(got, t[col].to_numpy(float), err_msg=f"{name}: {col}")
        # what is shown is the exact value, rounded
        shown = [s for _, s in page.column(f"summary-{name}", "completeness")]
        assert shown == [f"{v:.4f}" for v in t["completeness"]]
        # status totals: one row per table, sums of the cells
        row = [r for r in page.tables["status-totals"]["rows"] if r[0][0] == name][0]
        cols = page.tables["status-totals"]["columns"][1:]
        assert [int(v) for v, _ in row[1:]] == [int(t[c].sum()) for c in cols]
    t = Table.read(run / C.SUMMARY_DIRNAME / "summary_all.ecsv")
    stats = page.kv("run-statistics")
    assert int(stats["sources injected"][0]) == int(t["n_input"].sum()) > 0
    assert int(stats["recovered and selected"][0]) == int(t["n_selected"].sum())


def test_fit_numbers_equal_the_fit_outputs(reported):
    run, _, html_text = reported
    page = _Page(html_text)
    summary = json.loads((run / "fit" / "summary.json").read_text())["fits"]["all"]
    np.testing.assert_array_equal(_exact(page.column("m50-all", "m50")),
                                  [r["m50"] for r in summary["m50"]])
    np.testing.assert_array_equal(_exact(page.column("m50-all", "lower_68")),
                                  [r["ci68"][0] for r in summary["m50"]])
    np.testing.assert_array_equal(_exact(page.column("veff-all", "median_mpc3")),
                                  summary["effective_volume"]["quoted"]["median_mpc3"])
    with fits.open(run / C.SELECTION_FUNCTION_NAME) as h:
        ppc = Table(h["PPC", 1].data)
        hd = h["DRAWS", 1].header
        params = Table(h["PARAMS", 1].data)
    verdict = page.tables["ppc-verdict"]["rows"][0]
    assert int(verdict[1][0]) == len(ppc) and int(verdict[2][0]) == int(np.sum(ppc["extreme"]))
    facts = page.kv("sf-fit-all")
    assert int(facts["sources"][0]) == hd["NSOURCES"]
    assert facts["adequate (PPC)"][0] == ("true" if hd["ADEQUATE"] else "false")
    np.testing.assert_array_equal(_exact(page.column("params-all", "median")), params["median"])


def test_summary_says_in_plain_words_what_was_simulated_m50_the_model_and_the_fit_time(reported):
    run, _, html_text = reported
    page = _Page(html_text)
    manifest = json.loads((run / C.MANIFEST_NAME).read_text())
    fs = json.loads((run / "fit" / "summary.json").read_text())
    t = Table.read(run / C.SUMMARY_DIRNAME / "summary_all.ecsv")
    text = re.sub(r"<[^>]+>", "", re.search(r'<p id="summary-simulated">(.*?)</p>', html_text).group(1))
    n_in = int(t["n_input"].sum())
    assert text.startswith(f"{n_in} artificial galaxies were injected into 1 field")
    assert f"at {len(t)} grid cells: redshift z = 8, 10 × f160w magnitude m = 11 values from 23.5 to 28.5" \
        in text
    # m50 per field (one field, one pooled fit: the fit's m50) with its 68 % interval
    (field,) = manifest["fields"]
    # at the simulated redshifts (8 and 10; the fit summary also has 8.5, 9 and 9.5)
    m50 = [r for r in fs["fits"]["all"]["m50"] if r["z"] in manifest["z_values"]]
    assert sorted(r["z"] for r in m50) == sorted(manifest["z_values"])
    assert [v for v, _ in page.column("summary-m50", "field")] == [field] * len(m50)
    np.testing.assert_array_equal(_exact(page.column("summary-m50", "m50")), [r["m50"] for r in m50])
    np.testing.assert_array_equal(_exact(page.column("summary-m50", "upper_68")),
                                  [r["ci68"][1] for r in m50])
    r = m50[0]
    assert page.column("summary-m50", "m50_text")[0][1] == (
        f"{r['m50']:.2f} +{r['ci68'][1] - r['m50']:.2f}/−{r['m50'] - r['ci68'][0]:.2f}")
    # the depth of the field, from the manifest's area-by-depth distribution
    assert [v for v, _ in page.column("summary-depth", "field")] == [field]
    assert float(page.column("summary-depth", "depth_median")[0][0]) > 20
    # the model kept, why, and the fit's own clock
    fit_text = html.unescape(re.search(r'<p id="summary-fit">(.*?)</p>', html_text).group(1))
    e = fs["fits"]["all"]
    assert f"the {e['model']} completeness step was kept — {e['model_kept_because']}" in fit_text
    assert f"The fit took {fs['wall_time_s']:.1f} s of wall-clock time" in fit_text
    # the raw FITS keywords are no longer the summary: only in a closed <details>
    head = html_text[:html_text.index('id="sf-primary"')]
    assert head.rfind("<details>") > head.rfind("</details>")


def test_every_count_of_cells_is_named_and_defined(reported):
    """Three different counts were all called "n_cells" (or "cells"), undefined."""
    run, _, html_text = reported
    page = _Page(html_text)
    fs = json.loads((run / "fit" / "summary.json").read_text())
    columns = {c for t in page.tables.values() for c in t["columns"]}
    keys = {k for t in page.tables.values() for k in t["keys"]}
    assert not {"n_cells", "cells", "(z, m) cells"} & (columns | keys)
    terms = re.search(r'<dl id="cell-terms">(.*?)</dl>', html_text).group(1)
    assert re.findall(r"<dt>(.*?)</dt>", terms) == ["grid cells", "likelihood groups", "PPC cells"]
    with fits.open(run / C.SELECTION_FUNCTION_NAME) as h:
        n_ppc, ncells = len(h["PPC", 1].data), h["DRAWS", 1].header["NCELLS"]
    assert int(page.column("fit-statistics", "n_likelihood_groups")[0][0]) == \
        fs["fits"]["all"]["n_cells"] == ncells
    assert int(page.kv("sf-fit-all")["likelihood groups"][0]) == ncells
    assert int(page.column("ppc-verdict", "n_ppc_cells")[0][0]) == n_ppc
    t = Table.read(run / C.SUMMARY_DIRNAME / "summary_all.ecsv")
    assert int(page.kv("run-statistics")["grid cells (simulated z, m pairs)"][0]) == len(t)


def test_images_carry_their_own_size_and_are_wide_enough_to_read(reported):
    """Before: no size on the <img>, PNGs ~600 px wide with 7 pt legends."""
    _, before, after = reported
    for text in (before, after):
        for img in _Page(text).images:
            png = base64.b64decode(img["src"].split(",", 1)[1])
            w, h = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
            assert (int(img["width"]), int(img["height"])) == (w, h)
            assert w >= 800, (img.get("alt"), w)


def test_every_image_is_an_embedded_png_that_decodes(reported):
    import matplotlib.image as mpimg

    _, before, after = reported
    for text in (before, after):
        for img in _Page(text).images:
            src = img["src"]
            assert src.startswith("data:image/png;base64,")
            data = base64.b64decode(src.split(",", 1)[1], validate=True)
            a = mpimg.imread(io.BytesIO(data), format="png")
            assert a.ndim == 3 and a.shape[0] > 100 and a.shape[1] > 100
            assert float(a[..., :3].std()) > 0.02          # not a blank canvas
            assert img.get("alt")


def test_page_is_self_contained(reported):
    _, before, after = reported
    for text in (before, after):
        page = _Page(text)
        assert not re.search(r"(?i)\b(https?:|ftp:)//|\bwww\.", text)
        assert "<script" not in text.lower()
        for tag, a in page.attrs_all:
            for key in ("src", "href"):
                if key in a:
                    assert a[key].startswith(("data:", "#")), (tag, a[key][:60])
            assert not (tag == "link" and a.get("rel") == "stylesheet")


def test_report_of_an_unfitted_run_says_so(reported):
    _, before, _ = reported
    page = _Page(before)
    for sid in SECTIONS:
        assert sid in page.ids
    assert before.count("not fitted") >= 3
    assert {"fig-status", "fig-area-by-depth"} <= set(page.ids)
    assert not {"fig-completeness-all", "fig-ppc-all", "fig-veff-all"} & set(page.ids)
    assert len(page.images) == 2


def test_adaptive_rounds_are_shown_when_the_run_has_them(reported):
    from glaciar import report

    run, _, _ = reported
    path = run / ADAPTIVE_ROUNDS_NAME
    # As glaciar.pipeline.adaptive logs them.
    rounds = [{"round": 0, "n_sources": 500, "max_sd": 0.081, "max_sd_at": [9.0, 26.5],
               "cells": [{"z": 9.0, "mag": 26.5, "n_iterations": 3},
                         {"z": 9.5, "mag": 27.0, "n_iterations": 1}],
               "simulated": {"n_tasks_run": 4, "cpu_seconds": 2.5}},
              {"round": 1, "n_sources": 900, "max_sd": 0.043, "max_sd_at": [9.5, 27.0],
               "stop": "budget: 900 of 900 sources spent"}]
    try:
        path.write_text(json.dumps(rounds))
        data = load_report_data(run)
        page = _Page(report._adaptive_section(data))
        assert "adaptive-none" not in page.ids
        np.testing.assert_array_equal(_exact(page.column("adaptive-rounds", "max_sd")), [0.081, 0.043])
        html = report._adaptive_section(data)
        assert "2 cells, z 9–9.5, m 26.5–27" in html and "4 tasks, 2.5 s CPU" in html
        path.write_text(json.dumps({"round": 1}))
        with pytest.raises(ValueError, match="one per round"):
            load_report_data(run)
    finally:
        path.unlink()


# ------------------------------------------------------------------- headless Chromium
def _chromium():
    for name in (os.environ.get("GLACIAR_CHROMIUM"), "chromium", "chromium-browser",
                 "google-chrome", "google-chrome-stable"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


class _DevTools:
    """Chromium over the DevTools protocol on a pipe (``--remote-debugging-pipe``)."""

    def __init__(self, exe, timeout=90.0):
        import fcntl

        self.timeout = timeout
        r_cmd, self._w_cmd = os.pipe()          # Chromium reads commands on fd 3
        self._r_evt, w_evt = os.pipe()          # and writes replies and events on fd 4
        # fds >= 10 for the child, mapped to 3 and 4 by bash before exec
        r_c, w_e = (fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10) for fd in (r_cmd, w_evt))
        os.close(r_cmd)
        os.close(w_evt)
        self._profile = tempfile.mkdtemp(prefix="glaciar-chromium-")
        args = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
                "--no-default-browser-check", "--disable-extensions", "--remote-debugging-pipe",
                f"--user-data-dir={self._profile}", "about:blank"]
        self.proc = subprocess.Popen(
            ["bash", "-c", f'exec "$@" 3<&{r_c} 4>&{w_e} {r_c}<&- {w_e}>&-', "chromium", *args],
            pass_fds=(r_c, w_e), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL)
        os.close(r_c)
        os.close(w_e)
        self._buf, self._id, self.events = b"", 0, []

    def send(self, method, params=None, session=None):
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self._w_cmd, json.dumps(msg).encode() + b"\0")
        return self._id

    def wait(self, pred):
        end = time.monotonic() + self.timeout
        while True:
            while b"\0" in self._buf:
                raw, self._buf = self._buf.split(b"\0", 1)
                msg = json.loads(raw)
                self.events.append(msg)
                if pred(msg):
                    return msg
            ready, _, _ = select.select([self._r_evt], [], [], max(0.0, end - time.monotonic()))
            if not ready:
                raise TimeoutError("Chromium did not answer in time")
            chunk = os.read(self._r_evt, 1 << 16)
            if not chunk:
                raise EOFError("Chromium closed the DevTools pipe")
            self._buf += chunk

    def call(self, method, params=None, session=None):
        i = self.send(method, params, session)
        reply = self.wait(lambda m: m.get("id") == i)
        assert "error" not in reply, reply
        return reply["result"]

    def close(self):
        try:
            self.send("Browser.close")
            self.proc.wait(20)
        except Exception:
            self.proc.kill()
            self.proc.wait(20)
        finally:
            os.close(self._w_cmd)
            os.close(self._r_evt)
            shutil.rmtree(self._profile, ignore_errors=True)


#: the browser window's width [CSS px] in the Chromium test
VIEWPORT_PX = 1280

_IMAGES_JS = """JSON.stringify({
  title: document.title,
  figures: document.querySelectorAll("figure").length,
  sections: Array.from(document.querySelectorAll("section")).map(s => s.id),
  column: document.querySelector("main").getBoundingClientRect().width,
  images: Array.from(document.images).map(i => ({
    id: i.closest("figure") ? i.closest("figure").id : null, complete: i.complete,
    width: i.naturalWidth, height: i.naturalHeight,
    shown: i.clientWidth}))})"""


def test_chromium_loads_the_page_without_console_errors_and_shows_its_figures(reported):
    exe = _chromium()
    if exe is None:
        pytest.skip("headless Chromium not found (Debian: apt-get install chromium; .ci/run "
                    "installs it where apt is available; or set GLACIAR_CHROMIUM)")
    import matplotlib.image as mpimg

    run, _, html_text = reported
    browser = _DevTools(exe)
    try:
        target = browser.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        sid = browser.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        for domain in ("Runtime", "Log", "Page"):
            browser.call(f"{domain}.enable", session=sid)
        # a laptop's window: 1280 CSS px (headless Chromium's default is 800)
        browser.call("Emulation.setDeviceMetricsOverride", {"width": VIEWPORT_PX, "height": 900,
                                                            "deviceScaleFactor": 1, "mobile": False},
                     session=sid)
        browser.call("Page.navigate", {"url": (run / REPORT_NAME).resolve().as_uri()}, session=sid)
        browser.wait(lambda m: m.get("method") == "Page.loadEventFired" and m.get("sessionId") == sid)
        res = browser.call("Runtime.evaluate", {"expression": _IMAGES_JS, "returnByValue": True},
                           session=sid)
        info = json.loads(res["result"]["value"])
    finally:
        browser.close()
    errors = [m["params"] for m in browser.events
              if m.get("method") == "Runtime.exceptionThrown"
              or (m.get("method") == "Runtime.consoleAPICalled"
                  and m["params"].get("type") in ("error", "assert"))
              or (m.get("method") == "Log.entryAdded"
                  and m["params"]["entry"].get("level") == "error")]
    assert errors == [], errors
    assert info["title"].startswith("glaciar report")
    assert info["sections"] == list(SECTIONS)
    assert info["figures"] == len(info["images"]) == len(FITTED_FIGURES)
    assert sorted(i["id"] for i in info["images"]) == sorted(FITTED_FIGURES)
    # every figure decoded by the browser, at the PNG's own size, and laid out on the page
    sizes = []
    for img in _Page(html_text).images:
        a = mpimg.imread(io.BytesIO(base64.b64decode(img["src"].split(",", 1)[1])), format="png")
        sizes.append((a.shape[1], a.shape[0]))
    for i in info["images"]:
        assert i["complete"] and i["width"] > 100 and i["height"] > 100, i
        # shown at one PNG pixel per CSS pixel (the size its fonts were drawn for), or
        # shrunk to the page's column only when wider than it; never under 800 px
        assert abs(i["shown"] - min(i["width"], info["column"])) <= 1, i
        assert i["shown"] >= 800, i
    assert sorted((i["width"], i["height"]) for i in info["images"]) == sorted(sizes)
    assert math.isfinite(sum(i["shown"] for i in info["images"]))


def test_pooled_depth_aware_fit_gives_each_field_its_own_m50(tmp_path):
    """A pooled depth-aware fit: C(m | d) = C(m − (d − d_ref)), so a field 1 mag deeper (one
    depth bin each) has its m50 exactly 1 mag fainter; before, every field showed the
    survey-averaged m50 of fit/summary.json."""
    from glaciar import report
    from glaciar.inference import SelectionFunction, SurfaceModel

    mdl = SurfaceModel.for_data(np.array([7.0, 8.0]), np.array([25.0, 27.0, 29.0]), depth_ref=27.5)
    da = {"shallow": (np.array([27.0, 27.05]), np.array([1.0])),
          "deep": (np.array([28.0, 28.05]), np.array([2.0]))}
    dom = {"z": (7.0, 8.0), "mag": (24.0, 30.0), "depth": (27.0, 28.05)}
    th = mdl.sample_prior(40, np.random.default_rng(0))
    # draws whose root is inside the simulated range for both fields at both redshifts
    probe = SelectionFunction(mdl, th, depth_area=da, domain=dom)
    ok = np.all([np.isfinite(probe.magnitude_at(0.5, [7.0, 8.0], field=f).draws).all(axis=1)
                 for f in da], axis=0)
    assert ok.sum() >= 3
    sf = SelectionFunction(mdl, th[ok], np.linspace(7, 8, 5), np.linspace(24, 30, 13),
                           meta={"fields": list(da)}, field="all", depth_area=da, domain=dom)
    path = tmp_path / C.SELECTION_FUNCTION_NAME
    path.write_bytes(SelectionFunction.to_bytes([sf], {"fields": list(da)}))
    pooled_m50 = [{"z": 7.0, "m50": 0.0, "ci68": [0.0, 0.0]}, {"z": 8.0, "m50": 0.0, "ci68": [0.0, 0.0]}]
    data = {"selection_function": {"primary": {"DEPTHAW": True}},
            "fit_summary": {"fits": {"all": {"m50": pooled_m50}}},
            "manifest": {"fields": list(da)},
            "summaries": {"all": Table({"z": [7.0, 8.0]}).to_pandas()}}
    data["field_m50"] = report._pooled_field_m50(path, data, list(da))
    rows = {(f, z): (m50, lo, hi) for f, z, m50, lo, hi, fit in report._field_m50(data)}
    assert sorted(rows) == [("deep", 7.0), ("deep", 8.0), ("shallow", 7.0), ("shallow", 8.0)]
    for z in (7.0, 8.0):
        np.testing.assert_allclose(np.subtract(rows["deep", z], rows["shallow", z]), 1.0, atol=1e-6)


# ------------------------------------------------------------------------------
# The report's and the fit's figures, checked on the Figure objects (not on pixels).
#
# * glaciar never changes the user's matplotlib backend nor touches pyplot (a notebook's
#   inline figures keep working after a glaciar plot);
# * legends name simulated values only; V_eff is on a log axis; a cell without data has
#   no point; figures are drawn at a readable size.
#
# All data are synthetic and tiny (no run, no fit; tests/figure_cases.py): ~3 s in all.
# ------------------------------------------------------------------------------
def _texts(fig):
    from matplotlib.text import Text

    return [t for t in fig.findobj(Text) if t.get_text().strip() and t.get_visible()]


def _errorbar_x(ax):
    """x of every error-bar point drawn on ``ax``."""
    from matplotlib.container import ErrorbarContainer

    return np.concatenate([c.lines[0].get_xdata() for c in ax.containers
                           if isinstance(c, ErrorbarContainer)] or [np.empty(0)])


def _report_data():
    """What load_report_data returns, for a fitted run of SIM_Z × SIM_M (one field)."""
    zg, mg = np.linspace(6.0, 7.3, 24), np.linspace(25.5, 29.0, 36)
    zz, mm = np.meshgrid(zg, mg, indexing="ij")
    c = 1 / (1 + np.exp((mm - 27.5 + 0.1 * (zz - 6)) / 0.3))
    s = np.clip(1.2 - 0.1 * (zz - 6) - 0.05 * (mm - 26), 0, 1)
    shift = np.array([0.0, -0.1, 0.1, -0.2, 0.2])[:, None, None]   # planes 0.5, 16, 84, 2.5, 97.5 %
    q = lambda g: np.clip(g[None] + shift, 0, 1)                     # noqa: E731
    rows = []
    for z in SIM_Z:
        for m in SIM_M:
            n = 40
            k = 0 if m == 28.5 else int(n * (1 / (1 + np.exp((m - 27.5) / 0.3))))
            rows.append({"z": z, "mag": m, "n_input": n, "n_recovered": k, "n_selected": k // 2})
    summary = pd.DataFrame(rows)
    fit = {"field": "all", "draws_header": {"SELFIT": True},
           "C_GRID": {"q": q(c), "z": zg, "m": mg}, "SR_GRID": {"q": q(s), "z": zg, "m": mg},
           "P_GRID": {"q": q(c * s), "z": zg, "m": mg}}
    manifest = {"z_values": list(SIM_Z), "mag_values": list(SIM_M), "fields": ["f1"],
                "magnitude_type": "apparent", "detection_band": "f160w"}
    return {"manifest": manifest, "summaries": {"all": summary, "f1": summary},
            "selection_function": {"fits": [fit], "primary": {}}, "fit_summary": None,
            "run_dir": "/tmp/run"}


@pytest.fixture(scope="module")
def curve_figures():
    """The C(m) and S(z) figures of the report's curves section (captured Figure objects)."""
    made = []
    real = plots.plot_quantile_curves

    def capture(*a, **k):
        made.append(real(*a, **k))
        return made[-1]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(plots, "plot_quantile_curves", capture)
        # the figures are read as objects: no PNG rendering (a 1×1 PNG header for the page)
        mp.setattr(plots, "png_bytes", lambda fig, dpi=None: bytes(16) + bytes([0, 0, 0, 1] * 2))
        report._curves_section(_report_data())
    assert len(made) == 2
    return made


def test_report_c_and_s_legends_list_only_simulated_values(curve_figures):
    c_fig, s_fig = curve_figures
    assert legend_labels(c_fig.axes[0]) == ["z = 6", "z = 6.5", "z = 7.3"]
    assert legend_labels(s_fig.axes[0]) == ["m = 26", "m = 27", "m = 28.5"]


def test_report_curves_are_the_stored_quantiles_at_the_simulated_value(curve_figures):
    """z = 6 is a grid row: that row of C_GRID's median plane; z = 6.5 lies between two rows:
    linear in z between them (before: the row nearest 6.5, z = 6.5087)."""
    g = _report_data()["selection_function"]["fits"][0]["C_GRID"]
    line = {ln.get_label(): ln for ln in curve_figures[0].axes[0].get_lines()}
    np.testing.assert_array_equal(line["z = 6"].get_ydata(), g["q"][0, 0])
    want = [np.interp(6.5, g["z"], g["q"][0, :, j]) for j in range(g["m"].size)]
    np.testing.assert_allclose(line["z = 6.5"].get_ydata(), want, rtol=0, atol=1e-12)


def test_report_draws_no_point_for_a_cell_without_recovered_sources(curve_figures):
    c_fig, s_fig = curve_figures
    # C: every cell has injected sources, so 3 magnitudes × 3 redshifts of points
    assert np.sort(_errorbar_x(c_fig.axes[0])).tolist() == sorted(list(SIM_M) * 3)
    # S at m = 28.5: nothing recovered, so no S point (not a 0.50 ± 0.34 from the prior)
    assert _errorbar_x(s_fig.axes[0]).size == 2 * len(SIM_Z)
    ys = np.concatenate([c.lines[0].get_ydata() for c in s_fig.axes[0].containers])
    assert not np.any(np.isclose(ys, 0.5))


def test_effective_volume_is_on_a_log_axis_showing_the_faint_end():
    m = np.linspace(24, 30, 25)
    v = 1e5 / (1 + np.exp((m - 28) / 0.25))        # falls by ~4 decades to m = 30
    fig = plots.plot_effective_volume(m, v, 0.8 * v, 1.2 * v, mag_label="m", title="V")
    ax = fig.axes[0]
    assert ax.get_yscale() == "log"
    lo, hi = ax.get_ylim()
    assert 0 < lo <= v[m <= 29.5].min() and hi >= 1.2 * v.max()


def test_effective_volume_leaves_out_zero_volume_instead_of_clipping():
    m = np.array([26.0, 27.0, 28.0, 29.0])
    v = np.array([1e5, 1e4, 1e2, 0.0])
    ax = plots.plot_effective_volume(m, v, v, v, mag_label="m").axes[0]
    y = ax.get_lines()[0].get_ydata()
    assert np.isnan(y[-1]) and np.all(y[:-1] == v[:-1])


def test_report_figures_are_drawn_at_a_readable_size():
    """Shown at one PNG pixel per CSS pixel: >= 800 px wide and no text under 9 pt (12.5 px)."""
    for name, fig in report_figures().items():
        png = plots.png_bytes(fig)
        width = int.from_bytes(png[16:20], "big")
        assert width >= 800, (name, width)
        small = [(t.get_text(), t.get_fontsize()) for t in _texts(fig) if t.get_fontsize() < 9]
        assert small == [], (name, small)


_NOTEBOOK_USER = """
    import sys, tempfile
    import matplotlib
    matplotlib.use("svg")                        # the user's choice (a notebook: inline)
    import numpy as np, pandas as pd
    from glaciar.plots import plot_summary_maps
    from glaciar.pipeline.figures import completeness_figure, selection_figure
    sys.path.insert(0, {tests!r})
    from figure_cases import report_figures, toy_sf
    summ = pd.DataFrame({{"z": [7.0, 7.0], "mag": [26.0, 27.0], "completeness": [0.9, 0.2],
                         "selection_total": [0.5, 0.1], "selection": [0.55, 0.5]}})
    plot_summary_maps(summ, tempfile.mkdtemp(), "f1")
    report_figures()
    sf = toy_sf(True)
    completeness_figure(sf), selection_figure(sf)
    print(matplotlib.get_backend(), "matplotlib.pyplot" in sys.modules)
"""


def test_plotting_leaves_the_users_backend_and_pyplot_alone(tmp_path):
    """Before: plot_summary_maps and the fit figures called matplotlib.use("Agg")."""
    code = textwrap.dedent(_NOTEBOOK_USER.format(tests=str(Path(__file__).parent)))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["svg", "False"], out.stdout


def test_no_glaciar_module_selects_a_backend_or_imports_pyplot():
    """Also covers figures no test above draws (``lf_figure``)."""
    bad = []
    for path in Path(glaciar.__file__).parent.rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        if "matplotlib" not in text and "pyplot" not in text:
            continue
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                    and node.func.attr == "use" and getattr(node.func.value, "id", "") == "matplotlib":
                bad.append((path.name, node.lineno, "matplotlib.use"))
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [f"{node.module}.{a.name}" for a in node.names]
                     if isinstance(node, ast.ImportFrom) and node.module else [])
            bad += [(path.name, node.lineno, n) for n in names if "pyplot" in n]
    assert bad == []
