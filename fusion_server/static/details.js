// Click for details on the live map page: the UAV, global track or fused object nearest the click
// (within 12 px) opens a small panel with what the server knows of it; Escape or a click elsewhere closes it.
'use strict';

(() => {
  const NEAR_PX = 12;
  const mapEl = document.getElementById('map');
  const panel = document.getElementById('details');
  let down = null;

  const fmtTime = (t) => (t ? new Date(t * 1000).toLocaleTimeString() : '-');
  const fmt = (v, digits) => (typeof v === 'number' ? v.toFixed(digits) : '-');

  function candidates(map) {
    const s = map.state;
    const out = [];
    for (const u of s.uavs) {
      if (!u.state) continue;
      const st = u.state;
      out.push({ kind: 'uav', id: u.id, lat: st.lat, lon: st.lon, title: `UAV ${u.id}`, rows: [
        ['status', u.online ? 'online' : 'offline'], ['height', `${fmt(st.height_m, 1)} m`],
        ['gimbal pitch', `${fmt(st.pitch_deg, 1)}°`], ['heading', `${fmt(st.heading_deg, 1)}°`],
        ['position', `${fmt(st.lat, 6)}, ${fmt(st.lon, 6)}`], ['last seen', fmtTime(u.last_seen)],
        ['tiles covered', String(u.tiles ?? '-')]] });
    }
    for (const f of s.tracks) {
      const p = f.properties;
      const [lon, lat] = f.geometry.coordinates;
      const speed = Math.hypot(...(p.vel_en || [0, 0]));
      out.push({ kind: 'track', id: String(p.gid), lat, lon, title: `${p.cls} #${p.gid}`, rows: [
        ['status', p.status], ['score', fmt(p.score, 2)], ['speed', `${fmt(speed, 2)} m/s`],
        ['position', `${fmt(lat, 6)}, ${fmt(lon, 6)}`], ['first seen', fmtTime(p.created)],
        ['last update', fmtTime(p.last_update)],
        ['seen by', (p.active_members || []).map((m) => m[0]).join(', ') || 'nobody now'],
        ['history', `${(p.history || []).length} points`]] });
    }
    for (const f of s.objects) {
      const [lon, lat] = f.geometry.coordinates;
      out.push({ kind: 'object', id: `${fmt(lat, 6)},${fmt(lon, 6)}`, lat, lon,
        title: `fused ${f.properties.cls}`, rows: [['joint map value', fmt(f.properties.score, 3)],
          ['position', `${fmt(lat, 6)}, ${fmt(lon, 6)}`]] });
    }
    return out;
  }

  function nearest(map, px, py) {
    let best = null, bestD = NEAR_PX;
    for (const c of candidates(map)) {
      const [x, y] = map.toScreen(c.lat, c.lon);
      const d = Math.hypot(x - px, y - py);
      if (d <= bestD) { best = c; bestD = d; }
    }
    return best;
  }

  function show(c, px, py) {
    panel.replaceChildren();
    const h = document.createElement('b');
    h.textContent = c.title;
    panel.append(h);
    const table = document.createElement('table');
    for (const [k, v] of c.rows) {
      const tr = table.insertRow();
      tr.insertCell().textContent = k;
      tr.insertCell().textContent = v;
    }
    panel.append(table);
    panel.dataset.kind = c.kind;
    panel.dataset.id = c.id;
    panel.style.left = `${Math.min(px + 14, mapEl.clientWidth - 230)}px`;
    panel.style.top = `${Math.max(8, py - 20)}px`;
    panel.hidden = false;
  }

  function hide() { panel.hidden = true; panel.dataset.kind = ''; panel.dataset.id = ''; }

  mapEl.addEventListener('mousedown', (e) => { down = [e.clientX, e.clientY]; });
  mapEl.addEventListener('click', (e) => {
    const map = window.uavmmMap;
    if (!map || (down && Math.hypot(e.clientX - down[0], e.clientY - down[1]) > 4)) return;  // a drag
    const rect = mapEl.getBoundingClientRect();
    const px = e.clientX - rect.left, py = e.clientY - rect.top;
    const c = nearest(map, px, py);
    if (c) show(c, px, py); else hide();
  });
  window.addEventListener('keydown', (e) => { if (e.key === 'Escape') hide(); });
})();
