// uPlot charts (vendor/uplot-1.6.32): static plots (preview, trends) and rolling live plots.
import { clinicDateTime, clinicZoneName } from "./language.js";
import { h } from "./ui.js";

export const PALETTE = ["#0b4fa8", "#d1495b", "#00798c", "#edae49", "#6a4c93", "#30638e",
                        "#2e933c", "#b5179e", "#8d6e63", "#ff6f00", "#37474f", "#7cb342"];

function chartWidth(host) { return Math.max(320, (host.clientWidth || 600) - 12); }

// series: [{label, color?, dash?}], unit: axis unit shown in the title and on every value.
// xTime: x holds dates (POSIX seconds), labelled as dates. A series with pointsOnly draws marks, no line.
function options(title, unit, series, { height = 240, xLabel = "time (s)", yRange, ySoft = 1, xTime = false } = {}) {
  return {
    title: `${title} (${unit})`,
    // Date axes in the clinic's zone (as every date of the console), not the browser's.
    tzDate: (ts) => (clinicZoneName() ? uPlot.tzDate(new Date(ts * 1000), clinicZoneName()) : new Date(ts * 1000)),
    width: 600,
    height,
    // A flat signal keeps a readable axis (±ySoft) instead of uPlot's default 0–100.
    // Dates: a single day still gets a readable axis (a day either side) instead of years.
    scales: { x: xTime ? { time: true, range: (u, min, max) => (max - min < 86400 ? [min - 86400, max + 86400] : [min, max]) } : { time: false }, y: { range: yRange || ((u, min, max) => [Math.min(min ?? 0, -ySoft), Math.max(max ?? 0, ySoft)]) } },
    axes: [
      { label: xLabel, stroke: "#111", grid: { stroke: "#ddd" }, font: "14px system-ui", labelFont: "bold 14px system-ui" },
      { label: unit, stroke: "#111", grid: { stroke: "#ddd" }, font: "14px system-ui", labelFont: "bold 14px system-ui", size: 64 },
    ],
    legend: { live: true },
    series: [
      xTime ? { label: "date", value: (u, v) => (v == null ? "—" : clinicDateTime(new Date(v * 1000))) }
        : { label: "t", value: (u, v) => (v == null ? "—" : `${v.toFixed(2)} s`) },
      ...series.map((s, i) => ({
        label: s.label,
        stroke: s.color || PALETTE[i % PALETTE.length],
        width: s.width || 2,
        dash: s.dash,
        spanGaps: Boolean(s.spanGaps),
        ...(s.points ? { points: { show: true, size: s.points, fill: s.color } } : {}),
        ...(s.pointsOnly ? { paths: () => null } : {}),
        value: (u, v) => (v == null ? "—" : `${v.toFixed(s.digits ?? 2)} ${unit}`),
      })),
    ],
  };
}

export function staticChart(host, title, unit, x, ys, series, opts = {}) {
  const box = h("div.chart", { role: "img", "aria-label": `${title} chart, ${unit}` });
  host.append(box);
  const plot = new uPlot(options(title, unit, series, opts), [x, ...ys], box);
  plot.setSize({ width: chartWidth(box), height: opts.height || 240 });
  return plot;
}

// A rolling window of `windowS` seconds, fed one sample at a time and redrawn at most ~12 times a second.
export class LiveChart {
  constructor(host, title, unit, series, { windowS = 20, height = 220, yRange, ySoft = 1 } = {}) {
    this.box = h("div.chart", { role: "img", "aria-label": `${title}, live chart, ${unit}`, dataset: { chart: title } });
    host.append(this.box);
    this.windowS = windowS;
    this.data = [[], ...series.map(() => [])];
    this.plot = new uPlot(options(title, unit, series, { height, yRange, ySoft }), this.data, this.box);
    this.plot.setSize({ width: chartWidth(this.box), height });
    this.pending = false;
    this.samples = 0;
  }
  push(t, values) {
    this.data[0].push(t);
    values.forEach((v, i) => this.data[i + 1].push(Number.isFinite(v) ? v : null));
    while (this.data[0].length && this.data[0][0] < t - this.windowS) this.data.forEach((column) => column.shift());
    this.samples += 1;
    if (!this.pending) {
      this.pending = true;
      setTimeout(() => { this.pending = false; this.plot.setData(this.data); }, 80);
    }
  }
  reset() { this.data = this.data.map(() => []); this.plot.setData(this.data); }
  resize() { this.plot.setSize({ width: chartWidth(this.box), height: this.plot.height }); }
}
