// Time slider of the live page: replays the global tracks from the server's stored history (/v1/history).
// Live, the slider sits at its right end and follows the newest row; dragged back, the tracks are drawn
// where they were at that time (interpolated between history rows, with the last two minutes as trails)
// while the heatmap and the UAVs stay live. "live" (or dragging to the right end) returns.
'use strict';

(() => {
  const map = window.uavmmMap;
  const $ = (id) => document.getElementById(id);
  const slider = $('time-slider'), label = $('time-label'), liveButton = $('time-live'), box = $('timeline');
  const RANGE_MS = 10000;      // how often the slider's ends are refreshed
  const TRAIL_S = 120;         // history drawn behind each replayed track
  const GAP_S = 5;             // a track is shown up to this long after its last row

  let range = null;            // [first, last] history time, seconds since the epoch
  let history = null;          // features of /v1/history with their rows
  let historyAt = 0;           // when `history` was fetched (ms)

  const fmt = (t) => new Date(t * 1000).toLocaleTimeString();

  async function refreshRange() {
    try {
      const answer = await map.getJson('/v1/history?rows=false');
      range = answer.time_range;
      slider.disabled = !range;
      if (range) {
        slider.min = String(Math.floor(range[0]));
        slider.max = String(Math.ceil(range[1]));
        if (!map.state.replay) slider.value = slider.max;
      }
    } catch (e) { /* the map's own poll reports the server's state */ }
    setTimeout(refreshRange, RANGE_MS);
  }

  // position of a track at t from its rows [t, lat, lon] (sorted), or null when it has none then
  function positionAt(rows, t) {
    if (!rows.length || t < rows[0][0] || t > rows[rows.length - 1][0] + GAP_S) return null;
    let lo = 0, hi = rows.length - 1;
    while (lo < hi) {           // last row at or before t
      const mid = (lo + hi + 1) >> 1;
      if (rows[mid][0] <= t) lo = mid; else hi = mid - 1;
    }
    const a = rows[lo], b = rows[lo + 1];
    if (!b || b[0] <= a[0]) return [a[1], a[2], lo];
    const f = Math.max(0, Math.min(1, (t - a[0]) / (b[0] - a[0])));
    return [a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2]), lo];
  }

  function tracksAt(t) {
    const out = [];
    for (const feature of history || []) {
      const rows = feature.properties.history || [];
      const at = positionAt(rows, t);
      if (!at) continue;
      const [lat, lon, index] = at;
      const trail = rows.slice(0, index + 1).filter((r) => r[0] >= t - TRAIL_S);
      out.push({ ...feature, geometry: { type: 'Point', coordinates: [lon, lat] },
                 properties: { ...feature.properties, status: 'tracked', history: trail } });
    }
    return out;
  }

  async function show(t) {
    if (!history || Date.now() - historyAt > RANGE_MS) {
      try {
        history = (await map.getJson('/v1/history')).features || [];
        historyAt = Date.now();
      } catch (e) { return; }
    }
    map.state.replay = { t, tracks: tracksAt(t) };
    map.state.tracks = map.state.replay.tracks;
    box.dataset.mode = 'replay';
    label.textContent = `${fmt(t)} (replay)`;
    liveButton.disabled = false;
    map.redraw();
  }

  function live() {
    map.state.replay = null;
    map.state.tracks = map.state.liveTracks;
    box.dataset.mode = 'live';
    label.textContent = 'live';
    liveButton.disabled = true;
    if (range) slider.value = slider.max;
    map.redraw();
  }

  slider.addEventListener('input', () => {
    const t = Number(slider.value);
    if (range && t >= Number(slider.max)) live(); else show(t);
  });
  liveButton.addEventListener('click', live);
  box.dataset.mode = 'live';
  window.uavmmTimeline = { show, live, tracksAt, positionAt };  // tests and debugging
  refreshRange();
})();
