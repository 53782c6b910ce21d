// The timeline: selected weight curves (solid), ground truth (dashed), key preview (dots), the
// per-frame marker residual strip below, and the playhead. Pure drawing on a 2D canvas.
const COLORS = ['#ff9f40', '#40c0ff', '#a0e060', '#ff6090', '#c080ff', '#ffe040', '#60ffd0', '#ff8060'];
const LEFT = 40, RES_H = 60, GAP = 14, AXIS_H = 16;
const STEPS = [0.1, 0.2, 0.5, 1, 2, 5, 10, 15, 30, 60, 120, 300, 600];

export function frameAt(canvas, ev, n) {
  const r = canvas.getBoundingClientRect();
  const x = (ev.clientX - r.left) * (canvas.width / r.width);
  return Math.round(((x - LEFT) / (canvas.width - LEFT - 4)) * (n - 1));
}

export function drawTimeline(canvas, s) {
  const g = canvas.getContext('2d');
  const W = canvas.width, H = canvas.height, n = s.meta.n_frames;
  const top = 4, curveH = H - RES_H - GAP - top - 4 - AXIS_H;
  const X = (t) => LEFT + (t / Math.max(n - 1, 1)) * (W - LEFT - 4);
  const Yw = (v) => top + (1 - Math.max(-0.1, Math.min(1.1, v))) * curveH / 1.0;
  g.fillStyle = '#15161a'; g.fillRect(0, 0, W, H);
  g.strokeStyle = '#333'; g.lineWidth = 1;
  for (const v of [0, 0.5, 1]) { g.beginPath(); g.moveTo(LEFT, Yw(v)); g.lineTo(W, Yw(v)); g.stroke(); }
  g.fillStyle = '#888'; g.font = '10px sans-serif';
  g.fillText('1', 4, Yw(1) + 4); g.fillText('0', 4, Yw(0) + 4);
  const step = Math.max(1, Math.floor(n / (W - LEFT)));
  const line = (arr, dash) => {
    g.setLineDash(dash); g.beginPath();
    for (let t = 0; t < n; t += step) { const x = X(t), y = Yw(arr[t]); t ? g.lineTo(x, y) : g.moveTo(x, y); }
    g.stroke(); g.setLineDash([]);
  };
  s.selected.forEach((j, k) => {
    g.strokeStyle = COLORS[k % COLORS.length]; g.lineWidth = 1.2;
    line(s.curves.weights[j], []);
    if (s.curves.truth) { g.globalAlpha = 0.6; line(s.curves.truth[j], [4, 3]); g.globalAlpha = 1; }
    const key = s.keys && s.keys.shapes[s.names[j]];
    if (key) {
      g.fillStyle = COLORS[k % COLORS.length];
      key.frames.forEach((f, i) => { g.fillRect(X(f) - 2, Yw(key.values[i]) - 2, 4, 4); });
    }
    g.fillStyle = COLORS[k % COLORS.length];
    g.fillText(s.names[j], LEFT + 4 + 110 * k, top + 10);
  });
  const r = s.curves.residual, rtop = H - RES_H - 2 - AXIS_H;
  let rmax = 0; for (const v of r) rmax = Math.max(rmax, v);
  rmax = rmax || 1;
  g.strokeStyle = '#e05050'; g.beginPath();
  for (let t = 0; t < n; t += step) { const x = X(t), y = rtop + RES_H * (1 - r[t] / rmax); t ? g.lineTo(x, y) : g.moveTo(x, y); }
  g.stroke();
  g.fillStyle = '#e05050';
  g.fillText(`residual (max ${rmax.toFixed(2)} mm)`, 4, rtop - 3);
  const axis = timeAxis(g, X, n, s.meta.rate, W, H);
  g.strokeStyle = '#fff'; g.beginPath(); g.moveTo(X(s.frame), 0); g.lineTo(X(s.frame), H - AXIS_H); g.stroke();
  return axis;
}

// seconds along the bottom: the largest round step that leaves ~70 px between labels
function timeAxis(g, X, n, rate, W, H) {
  const duration = (n - 1) / rate;
  const step = STEPS.find((d) => duration / d <= (W - LEFT) / 70) || STEPS[STEPS.length - 1];
  const y = H - AXIS_H, ticks = [];
  g.strokeStyle = '#888'; g.fillStyle = '#aaa'; g.font = '10px sans-serif'; g.lineWidth = 1;
  g.beginPath(); g.moveTo(LEFT, y); g.lineTo(W, y); g.stroke();
  for (let k = 0; k * step <= duration + 1e-9; k++) {
    const t = k * step, x = X(t * rate);
    g.beginPath(); g.moveTo(x, y); g.lineTo(x, y + 4); g.stroke();
    const text = `${+t.toFixed(1)} s`;
    g.fillText(text, Math.min(x - g.measureText(text).width / 2, W - g.measureText(text).width - 2), H - 2);
    ticks.push(t);
  }
  return { step, ticks, y };
}
