// The error of a mesh against its level, from the few points the server
// summarises (GET /meshes/{id}: error_curve) plus the exact error of the base
// level (from its /lod document).
//
// Packets do not carry errors, so between known points the error is
// interpolated, linearly in log(level): the summary samples levels
// geometrically (ratios 1, 1/2, 1/4, 1/10, ...). The error is monotone
// (non-increasing in level) on the server, and stays so here.

export class ErrorCurve {
  constructor(info, baseError) {
    const points = new Map([[info.base_vertices, baseError]]);
    for (const point of info.error_curve) points.set(point.vertices, point.error);
    this.points = [...points].map(([level, error]) => ({ level, error }))
      .sort((a, b) => a.level - b.level);
    this.base = info.base_vertices;
    this.full = info.vertices;
  }

  get maxError() {
    return this.points[0].error;
  }

  // The known points bracketing level, and where level lies between them (0..1).
  bracket(level) {
    const { points } = this;
    let i = 1;
    while (i < points.length - 1 && points[i].level < level) i++;
    const a = points[Math.max(0, i - 1)], b = points[Math.min(i, points.length - 1)];
    if (a.level === b.level) return { a, b, x: 0 };
    const x = (Math.log(level) - Math.log(a.level)) / (Math.log(b.level) - Math.log(a.level));
    return { a, b, x: Math.min(1, Math.max(0, x)) };
  }

  // The (interpolated) error at a level, mesh units.
  errorAt(level) {
    const { a, b, x } = this.bracket(level);
    return a.error + (b.error - a.error) * x;
  }

  // Whether errorAt(level) is a value the server reported, not an interpolation.
  isExact(level) {
    return this.points.some((point) => point.level === level);
  }

  // The coarsest level whose error is at most `error` (full detail if none).
  levelFor(error) {
    const { points } = this;
    if (points[0].error <= error) return this.base;
    for (let i = 1; i < points.length; i++) {
      const a = points[i - 1], b = points[i];
      if (b.error > error) continue;
      // error lies in [b.error, a.error): invert the interpolation on this segment
      const x = (a.error - error) / (a.error - b.error);
      const level = Math.exp(Math.log(a.level) + x * (Math.log(b.level) - Math.log(a.level)));
      return Math.min(b.level, Math.max(a.level, Math.ceil(level)));
    }
    return this.full;
  }

  // The level to move to from `level` (held or being moved to) for a view
  // that allows an error of `allowed` mesh units (the budget in pixels over
  // the pixels a unit covers), or null to stay: finer as soon as the view
  // needs more; coarser only once the level's error is under allowed /
  // hysteresis, and then to the level of allowed / sqrt(hysteresis), so a view
  // moving back and forth across one distance neither refines nor coarsens at
  // every step.
  follow(level, allowed, hysteresis = 2) {
    const needed = this.levelFor(allowed);
    if (needed > level) return needed;
    if (this.errorAt(level) >= allowed / hysteresis) return null;
    const coarser = Math.max(needed, this.levelFor(allowed / Math.sqrt(hysteresis)));
    return coarser < level ? coarser : null;
  }
}
