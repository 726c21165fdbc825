"""The HTML leaderboard in a real headless browser (Debian's chromium, installed by
``.ci/setup``): no console message, no script error, every image loads (naturalWidth > 0),
no request leaves the folder; a screenshot is saved (``VVTBENCH_SCREENSHOTS=DIR`` keeps a copy).

No browser-driver dependency: the page is copied beside itself with a probe script first in
<head> (it records console calls, script errors and failed loads, then writes its findings
into the DOM), loaded with ``--dump-dom``; chromium's own console log (stderr) is checked too.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess

import pytest
from test_leaderboard import make_run

from vvtbench.reporting.leaderboard import build

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="needs chromium (.ci/setup installs "
                                                          "Debian's chromium)")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--enable-logging=stderr", "--v=0", "--hide-scrollbars"]

PROBE = """<script>(function(){
var found={console:[],errors:[],failed:[]};
['log','info','warn','error','debug'].forEach(function(k){var f=console[k];
 console[k]=function(){found.console.push(k+': '+Array.prototype.join.call(arguments,' '));
 return f.apply(console,arguments);};});
window.addEventListener('error',function(e){var t=e.target;
 if(t&&t!==window&&(t.src||t.href)){found.failed.push(t.src||t.href);}
 else{found.errors.push(String(e.message));}},true);
window.addEventListener('load',function(){
 found.images=[].map.call(document.images,function(i){
  return {src:i.getAttribute('src'),ok:i.complete&&i.naturalWidth>0,w:i.naturalWidth};});
 found.viewport=document.documentElement.clientWidth;
 found.overflow=[].filter.call(document.querySelectorAll('table'),function(t){
  var box=t.parentElement.getBoundingClientRect(),r=t.getBoundingClientRect();
  return r.right>box.right+1||r.left<box.left-1||r.right>found.viewport+1;}).map(function(t){
  return (t.previousElementSibling||t.parentElement.previousElementSibling||{}).textContent+
  ': '+Math.round(t.getBoundingClientRect().width)+' px';});
 found.external=[].map.call(document.querySelectorAll('[src],[href]'),function(e){
  return e.getAttribute('src')||e.getAttribute('href');}).filter(function(u){
  return /^[a-z]+:/i.test(u)&&!/^(data|file):/i.test(u);});
 var p=document.createElement('pre');p.id='vvt-probe';p.textContent=JSON.stringify(found);
 document.body.appendChild(p);});})();</script>"""


def load_in_chromium(page, tmp_path, screenshot=None, width=1280):
    """(findings of the probe, chromium console lines) of ``page`` (an HTML file) in a window
    ``width`` pixels wide."""
    probe = page.with_name(".probe-" + page.name)
    text = page.read_text()
    probe.write_text(text.replace("<head>", "<head>" + PROBE, 1) if "<head>" in text
                     else PROBE + text)
    try:
        common = [CHROMIUM, *FLAGS, f"--user-data-dir={tmp_path / 'chromium-profile'}",
                  "--virtual-time-budget=10000", f"--window-size={width},1000"]
        r = subprocess.run([*common, "--dump-dom", probe.as_uri()], capture_output=True,
                           text=True, timeout=180)
        if screenshot is not None:
            subprocess.run([*common, f"--screenshot={screenshot}",
                            f"--window-size={width},2400", page.as_uri()],
                           capture_output=True, text=True, timeout=180)
    finally:
        probe.unlink(missing_ok=True)
    m = re.search(r'<pre id="vvt-probe">(.*?)</pre>', r.stdout, re.S)
    assert m, f"the page did not finish loading in chromium:\n{r.stderr[-2000:]}"
    import html

    found = json.loads(html.unescape(m.group(1)))
    console = [line for line in r.stderr.splitlines() if ":CONSOLE" in line]
    return found, console


def test_probe_catches_broken_pages(tmp_path):
    """The check itself fails on what it must catch: a missing image and a console error."""
    page = tmp_path / "bad.html"
    page.write_text("<!doctype html><html><head></head><body><img src='missing.png'>"
                    "<script>console.error('boom')</script></body></html>")
    found, console = load_in_chromium(page, tmp_path)
    assert [i["ok"] for i in found["images"]] == [False]
    assert found["console"] == ["error: boom"] and any("boom" in c for c in console)


@pytest.fixture(scope="module")
def board(tmp_path_factory):
    """The leaderboard of the synthetic run, built once: the tests below only read it."""
    root = tmp_path_factory.mktemp("board")
    return build(make_run(root / "run") / "results.csv", root / "lb")


def test_leaderboard_page_in_headless_chromium(board, tmp_path):
    out = board
    shot = tmp_path / "leaderboard.png"
    found, console = load_in_chromium(out / "index.html", tmp_path, screenshot=shot)
    assert not console and not found["console"] and not found["errors"], (console, found)
    assert not found["failed"] and not found["external"], found
    assert len(found["images"]) >= 8
    assert all(i["ok"] for i in found["images"]), [i for i in found["images"] if not i["ok"]]
    assert shot.is_file() and shot.stat().st_size > 10_000
    keep = os.environ.get("VVTBENCH_SCREENSHOTS")
    if keep:
        os.makedirs(keep, exist_ok=True)
        shutil.copy(shot, os.path.join(keep, "leaderboard.png"))


@pytest.mark.parametrize("width", [900, 1400])
def test_no_table_overflows_its_container(board, tmp_path, width):
    """At 900 and 1400 px every table fits inside its container and the window: cells wrap,
    nothing hides behind a horizontal scroll bar."""
    found, _ = load_in_chromium(board / "index.html", tmp_path, width=width)
    assert found["viewport"] <= width and found["viewport"] > width - 40, found["viewport"]
    assert not found["overflow"], found["overflow"]


def test_overflow_probe_catches_a_wide_table(tmp_path):
    page = tmp_path / "wide.html"
    cells = "".join(f"<td>{'x' * 30}</td>" for _ in range(40))
    page.write_text("<!doctype html><html><head></head><body><div><table style="
                    f"'white-space:nowrap'><tr>{cells}</tr></table></div></body></html>")
    found, _ = load_in_chromium(page, tmp_path, width=900)
    assert len(found["overflow"]) == 1
