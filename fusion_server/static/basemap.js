// Basemap layer of the live map page: XYZ tiles drawn under everything else, from the fusion server's
// --basemap (an MBTiles file it serves itself, or a tile URL the browser fetches). Nothing is fetched
// without --basemap: the page stays offline by default.
'use strict';

window.UavmmBasemap = (config, tokenQuery, onLoad) => {
  const TILE_PX = 256;
  const cache = new Map();  // "z/x/y" -> {img, ok}
  const MAX_CACHED = 512;
  const local = Boolean(config.local);

  function url(z, x, y) {
    const u = config.url.replace('{z}', z).replace('{x}', x).replace('{y}', y);
    return local ? u + (tokenQuery ? `?${tokenQuery.slice(1)}` : '') : u;
  }

  function tile(z, x, y) {
    const key = `${z}/${x}/${y}`;
    let entry = cache.get(key);
    if (!entry) {
      if (cache.size >= MAX_CACHED) cache.delete(cache.keys().next().value);
      entry = { img: new Image(), ok: false };
      entry.img.onload = () => { entry.ok = true; onLoad(); };
      entry.img.src = url(z, x, y);
      cache.set(key, entry);
    }
    return entry.ok ? entry.img : null;
  }

  // view: {mx, my, zoom} in normalised Web-Mercator; returns the number of tiles drawn
  function draw(ctx, view, w, h) {
    const z = Math.max(config.minzoom, Math.min(config.maxzoom, Math.round(view.zoom)));
    const n = Math.pow(2, z);
    const k = TILE_PX * Math.pow(2, view.zoom);  // world size in screen pixels
    const x0 = Math.max(0, Math.floor((view.mx - w / 2 / k) * n));
    const x1 = Math.min(n - 1, Math.floor((view.mx + w / 2 / k) * n));
    const y0 = Math.max(0, Math.floor((view.my - h / 2 / k) * n));
    const y1 = Math.min(n - 1, Math.floor((view.my + h / 2 / k) * n));
    if ((x1 - x0 + 1) * (y1 - y0 + 1) > 400) return 0;
    let drawn = 0;
    for (let x = x0; x <= x1; x++) {
      for (let y = y0; y <= y1; y++) {
        const img = tile(z, x, y);
        if (!img) continue;
        const sx = (x / n - view.mx) * k + w / 2, sy = (y / n - view.my) * k + h / 2;
        ctx.drawImage(img, sx, sy, k / n + 0.5, k / n + 0.5);  // +0.5: no seams between tiles
        drawn += 1;
      }
    }
    return drawn;
  }

  return { draw, attribution: config.attribution || '' };
};
