// A small plot of the error against the level (log scale: the levels the
// server summarises are spaced geometrically), with the level shown, the
// target being moved to, and in auto mode the error the budget allows.
//
// Signals in: 'mesh', 'level', 'target', 'budget', 'scene-shown'.

const MARGIN = { left: 6, right: 6, top: 8, bottom: 16 };
const COLORS = { curve: '#8fb3ff', point: '#dfe8ff', level: '#ffcf6e', target: '#ffcf6e80',
                 budget: '#7fd99a', text: '#9aa3b2' };

export class ErrorPlot {
  // viewer: the bus; canvas: the <canvas> drawn on.
  constructor(viewer, canvas) {
    this.canvas = canvas;
    this.curve = null;          // the mesh's ErrorCurve (curve.js), or null: nothing drawn
    this.level = this.target = this.budget = null;
    viewer.on('mesh', (detail) => {
      this.curve = detail.curve;
      this.level = this.target = detail.state.level;
      this.draw();
    });
    viewer.on('level', ({ state }) => {
      this.level = state.level;
      this.draw();
    });
    // a scene (animated.js) has a curve per part: none is drawn
    viewer.on('scene-shown', () => {
      this.curve = null;
      this.draw();
    });
    viewer.on('target', (value) => {
      this.target = value;
      this.draw();
    });
    // the error the pixel budget allows in auto mode, or null
    viewer.on('budget', (error) => {
      this.budget = error;
      this.draw();
    });
  }

  draw() {
    const { canvas, curve, level, target, budget } = this;
    const ratio = window.devicePixelRatio || 1;
    const width = canvas.clientWidth, height = canvas.clientHeight;
    canvas.width = Math.round(width * ratio);
    canvas.height = Math.round(height * ratio);
    const g = canvas.getContext('2d');
    g.setTransform(ratio, 0, 0, ratio, 0, 0);
    g.clearRect(0, 0, width, height);
    if (!curve) return;

    const span = Math.log(curve.full) - Math.log(curve.base) || 1;
    const x = (v) => MARGIN.left + (width - MARGIN.left - MARGIN.right) *
      (Math.log(v) - Math.log(curve.base)) / span;
    const y = (e) => height - MARGIN.bottom - (height - MARGIN.top - MARGIN.bottom) *
      (curve.maxError > 0 ? e / curve.maxError : 0);

    g.strokeStyle = COLORS.curve;
    g.lineWidth = 1.5;
    g.beginPath();
    for (let i = 0; i <= 100; i++) {
      const v = Math.exp(Math.log(curve.base) + span * i / 100);
      g[i ? 'lineTo' : 'moveTo'](x(v), y(curve.errorAt(v)));
    }
    g.stroke();
    g.fillStyle = COLORS.point;
    for (const point of curve.points) g.fillRect(x(point.level) - 1.5, y(point.error) - 1.5, 3, 3);

    if (budget !== null) {
      g.strokeStyle = COLORS.budget;
      g.setLineDash([4, 3]);
      g.beginPath();
      g.moveTo(MARGIN.left, y(Math.min(budget, curve.maxError)));
      g.lineTo(width - MARGIN.right, y(Math.min(budget, curve.maxError)));
      g.stroke();
      g.setLineDash([]);
    }
    for (const [v, color] of [[target, COLORS.target], [level, COLORS.level]]) {
      if (v === null) continue;
      g.strokeStyle = color;
      g.beginPath();
      g.moveTo(x(v), MARGIN.top);
      g.lineTo(x(v), height - MARGIN.bottom);
      g.stroke();
    }
    g.fillStyle = COLORS.text;
    g.font = '10px system-ui, sans-serif';
    g.textBaseline = 'bottom';
    g.fillText(`${curve.base}`, MARGIN.left, height);
    g.textAlign = 'right';
    g.fillText(`${curve.full} vertices`, width - MARGIN.right, height);
    g.textBaseline = 'top';
    g.fillText(`max error ${curve.maxError.toPrecision(3)}`, width - MARGIN.right, 0);
  }
}
