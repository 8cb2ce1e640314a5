"""The page people look at: ``index.html``, static, opened from disk (no server, nothing fetched
from the network), one row per input with a strip of mask-overlay thumbnails, the trajectory
plot, the verdict and the key numbers; a click on a column heading sorts by it (``#sort=KEY`` or
``#sort=-KEY`` in the address sorts on opening). ``mona-vo batch`` writes it over every input,
``mona-vo run`` for its one video.

The page checks its own pictures when it loads: ``<body data-images-loaded=N
data-images-broken=M>``, and a broken picture is replaced by the words "missing image", so a
browser (or a headless one in a test) sees at once whether every picture is there.
"""
from __future__ import annotations

import html
import math
import time
import urllib.parse
from pathlib import Path
from typing import Sequence

import numpy as np

from data_tools.atomic import atomic_path, write_text_atomic

STRIP_NAME = "overlay_strip.jpg"
PLOT_NAME = "trajectory.png"


class ThumbnailStrip:
    """Collects ``count`` evenly spaced frames of a run as small mask overlays (memory: the
    thumbnails only) and writes them side by side as one JPEG."""

    def __init__(self, n_frames: int, count: int = 5, height: int = 80):
        self.height = int(height)
        n = max(int(n_frames), 0)
        self.wanted = set(np.unique(np.linspace(0, n - 1, min(count, n)).round().astype(int)).tolist()) if n else set()
        self.thumbs: list[np.ndarray] = []
        self._seen = 0

    def add(self, frame) -> None:
        """frame: a :class:`mona_vo.pipeline.FrameOutput` (``image`` (H, W, 3) uint8 RGB, ``mask``
        (H, W) bool or None), in order."""
        i = self._seen
        self._seen += 1
        if i not in self.wanted:
            return
        import cv2

        from data_tools.overlay import draw_overlay

        drawn = draw_overlay(frame.image, frame.mask)
        h, w = drawn.shape[:2]
        width = max(1, round(w * self.height / h))
        self.thumbs.append(cv2.resize(drawn, (width, self.height), interpolation=cv2.INTER_AREA))

    def write(self, path: str | Path) -> bool:
        """Write the strip (JPEG); False when no frame was collected."""
        if not self.thumbs:
            return False
        import cv2

        gap = np.full((self.height, 3, 3), 255, np.uint8)
        parts = []
        for t in self.thumbs:
            parts += [t, gap]
        strip = np.concatenate(parts[:-1], axis=1)
        with atomic_path(path) as tmp:
            if not cv2.imwrite(str(tmp), cv2.cvtColor(strip, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85]):
                raise OSError(f"cannot write {path}")
        return True


# Sortable columns: (key, heading, how the value is shown).
_NUMBERS = (
    ("frames", "frames", "{:.0f}"),
    ("posed_share", "posed %", "pct"),
    ("low_confidence_share", "low-conf %", "pct"),
    ("mask_coverage", "mask %", "pct"),
    ("keyframes", "keyfr.", "{:.0f}"),
    ("map_segments", "maps", "{:.0f}"),
    ("reprojection_rmse_px", "RMSE px", "{:.2f}"),
    ("global_shift_pct", "shift %", "{:.2f}"),
    ("support_p10", "support", "{:.0f}"),
    ("seconds", "s", "{:.1f}"),
    ("frames_per_second", "frames/s", "{:.2f}"),
)

_CSS = """
body{font:14px/1.4 system-ui,sans-serif;margin:16px;color:#222}
h1{font-size:20px;margin:0 0 4px}
.summary{color:#555;margin-bottom:12px}
table{border-collapse:collapse}
th,td{border-bottom:1px solid #ddd;padding:3px 6px;vertical-align:middle;text-align:right}
th{background:#f3f3f3;cursor:pointer;user-select:none;white-space:nowrap;position:sticky;top:0}
th.sorted-asc::after{content:" \\25B2"} th.sorted-desc::after{content:" \\25BC"}
td.text,th.text{text-align:left}
.input{color:#777;font-size:11px;word-break:break-all;max-width:170px}
.usable{color:#0a0;font-weight:600} .unusable{color:#b60;font-weight:600} .failed{color:#c00;font-weight:600}
tr.failed-row td{background:#fff4f4}
.reason{font-size:12px;color:#844;max-width:200px;text-align:left;white-space:pre-line}
img.strip{height:40px;display:block} img.plot{height:72px;display:block}
td.node{font-size:11px;color:#777}
.missing{display:inline-block;color:#c00;font-size:12px;border:1px dashed #c00;padding:4px}
"""

_JS = """
(function(){
  var table=document.getElementById('clips'), body=table.tBodies[0];
  function val(td){var v=td.getAttribute('data-v'); if(v===null) v=td.textContent;
    var n=parseFloat(v); return (v!=='' && !isNaN(n) && isFinite(v)) ? n : String(v).toLowerCase();}
  function sortBy(key, desc){
    var ths=table.tHead.rows[0].cells, col=-1;
    for(var i=0;i<ths.length;i++){ths[i].classList.remove('sorted-asc','sorted-desc');
      if(ths[i].getAttribute('data-key')===key) col=i;}
    if(col<0) return;
    ths[col].classList.add(desc?'sorted-desc':'sorted-asc');
    var rows=Array.prototype.slice.call(body.rows);
    rows.sort(function(a,b){var x=val(a.cells[col]), y=val(b.cells[col]);
      var empty=function(v){return v==='';};
      if(empty(x)!==empty(y)) return empty(x)?1:-1;   // blanks last either way
      if(typeof x!==typeof y){x=String(x); y=String(y);}
      var c = x<y?-1:(x>y?1:0); return desc?-c:c;});
    rows.forEach(function(r){body.appendChild(r);});
    table.setAttribute('data-sorted', (desc?'-':'')+key);
  }
  var heads=table.tHead.rows[0].cells;
  for(var i=0;i<heads.length;i++){(function(th){th.addEventListener('click',function(){
    var key=th.getAttribute('data-key'); var desc=table.getAttribute('data-sorted')===key;
    sortBy(key, desc); history.replaceState(null,'','#sort='+(desc?'-':'')+key);});})(heads[i]);}
  var m=/sort=(-?)([a-z_]+)/.exec(location.hash); if(m) sortBy(m[2], m[1]==='-');
  function checkImages(){
    var imgs=document.images, ok=0, bad=0;
    for(var i=0;i<imgs.length;i++){var im=imgs[i];
      if(im.complete && im.naturalWidth>0) ok++; else {bad++;
        var s=document.createElement('span'); s.className='missing'; s.textContent='missing image';
        s.title=im.getAttribute('src'); if(im.parentNode) im.parentNode.replaceChild(s, im); i--;}}
    document.body.setAttribute('data-images-loaded', ok);
    document.body.setAttribute('data-images-broken', bad);
  }
  if(document.readyState==='complete') checkImages(); else window.addEventListener('load', checkImages);
})();
"""


def _fmt(value, how: str) -> tuple[str, str]:
    """(shown text, sort value) of one number."""
    if value is None or value == "" or (isinstance(value, float) and not math.isfinite(value)):
        return "-", ""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return html.escape(str(value)), html.escape(str(value))
    if how == "pct":
        return f"{100 * v:.1f}", repr(v)
    return how.format(v), repr(v)


def _href(*parts: str) -> str:
    return "/".join(urllib.parse.quote(p) for p in parts if p and p != ".")


def _row_html(row: dict, page_dir: Path, here: bool) -> str:
    e = html.escape
    name = str(row.get("name", ""))
    folder = "." if here else name
    status = row.get("status", "")
    usable = row.get("usable")
    if status == "failed":
        verdict, vclass, vsort = "failed", "failed", "0"
    elif usable in (True, "true", "True"):
        verdict, vclass, vsort = "usable", "usable", "2"
    else:
        verdict, vclass, vsort = "not usable", "unusable", "1"
    reason = str(row.get("reason") or "")
    if reason.startswith("not usable: "):
        reason = reason[len("not usable: "):].replace("; ", "\n")
    cells = []
    link = _href(folder) or "."
    cells.append(f'<td class="text" data-v="{e(name.lower())}"><a href="{e(link)}/">{e(name)}</a>'
                 f'<div class="input">{e(str(row.get("input", "")))}</div></td>')
    cells.append(f'<td class="text" data-v="{vsort}"><span class="{vclass}">{verdict}</span>'
                 f'{" (skipped: done earlier)" if status == "skipped" else ""}'
                 f'<div class="reason">{e(reason)}</div></td>')
    for fname, cls, alt in ((STRIP_NAME, "strip", "mask overlays"), (PLOT_NAME, "plot", "trajectory")):
        rel = _href(folder, fname)
        if status != "failed" and (page_dir / folder / fname).is_file():
            cells.append(f'<td class="text"><a href="{e(rel)}"><img class="{cls}" src="{e(rel)}" '
                         f'alt="{alt} of {e(name)}" loading="eager"></a></td>')
        else:
            cells.append('<td class="text">-</td>')
    frames = row.get("frames")
    values = dict(row)
    try:
        values["posed_share"] = float(row.get("frames_with_pose")) / float(frames) if frames else None
    except (TypeError, ValueError):
        values["posed_share"] = None
    for key, _, how in _NUMBERS:
        text, sort = _fmt(values.get(key), how)
        cells.append(f'<td data-v="{sort}">{text}</td>')
    cells.append(f'<td class="text node">{e(str(row.get("node") or ""))}</td>')
    cls = ' class="failed-row"' if status == "failed" else ""
    return f"<tr{cls}>" + "".join(cells) + "</tr>"


def write_index_html(path: str | Path, rows: Sequence[dict], *, title: str = "mona-vo",
                     here: bool = False, pending: int = 0) -> Path:
    """Write the page (atomically). ``rows``: batch.csv rows with ``usable``. ``here``: the
    page sits in the run's own folder (``run``), not one folder above it (``batch``).
    Pictures are linked only when the file is there."""
    path = Path(path)
    page_dir = path.parent
    e = html.escape
    heads = ['<th class="text" data-key="name">clip</th>', '<th class="text" data-key="verdict">verdict</th>',
             '<th class="text" data-key="strip">masks</th>', '<th class="text" data-key="plot">trajectory</th>']
    heads += [f'<th data-key="{k}">{e(h)}</th>' for k, h, _ in _NUMBERS]
    heads.append('<th class="text" data-key="node">node</th>')
    n_ok = sum(r.get("status") == "ok" for r in rows)
    n_skip = sum(r.get("status") == "skipped" for r in rows)
    n_fail = sum(r.get("status") == "failed" for r in rows)
    n_use = sum(r.get("usable") in (True, "true", "True") for r in rows)
    summary = (f"{len(rows)} inputs: {n_ok} ok, {n_skip} skipped (done earlier), {n_fail} failed; "
               f"{n_use} usable" + (f"; {pending} still running or not started" if pending else "")
               + f". Written {time.strftime('%Y-%m-%d %H:%M:%S')}.")
    body = "\n".join(_row_html(r, page_dir, here) for r in rows)
    text = (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{e(title)}</title><style>{_CSS}</style></head>\n<body>\n<h1>{e(title)}</h1>\n"
            f"<div class=\"summary\">{e(summary)} Click a heading to sort.</div>\n"
            f"<table id=\"clips\"><thead><tr>{''.join(heads)}</tr></thead>\n<tbody>\n{body}\n</tbody></table>\n"
            f"<script>{_JS}</script>\n</body></html>\n")
    write_text_atomic(path, text)
    return path
