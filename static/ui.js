// The panel: pick or upload a mesh, move the level (slider, number, keys),
// read the stats, change the settings.
//
// The slider is logarithmic in the level: a mesh's interesting coarse levels
// span a few hundred vertices, its fine ones hundreds of thousands.
//
// The mesh list refreshes itself while a mesh in it is queued or building.
// An id that the server does not know (a link to a deleted mesh, a typo, a
// path) is named in the status and never opened or listed.
//
// Signals out: 'open' ({ id }), 'goto' (a
// level), 'settings' (a key). In: 'mesh', 'level', 'target', 'status',
// 'settings', 'textures' (image bytes received).

const SLIDER_STEPS = 1000;
const LIST_REFRESH_MS = 2000;        // while a listed mesh is queued or building
const PENDING = new Set(['queued', 'building']);
const KEY_STEPS = { ArrowUp: 10, ArrowRight: 10, ArrowDown: -10, ArrowLeft: -10,
                    PageUp: 100, PageDown: -100 };
// The settings the panel edits: which key, how it is shown.
const CONTROLS = [
  { key: 'autoByDistance', label: 'stop at the error budget (auto level)', type: 'checkbox' },
  { key: 'errorBudgetPx', label: 'error budget (px)', type: 'number', min: 0.05, step: 0.05 },
  { key: 'shading', label: 'shading', options: ['smooth', 'flat'] },
  { key: 'wireframe', label: 'wireframe', type: 'checkbox' },
  { key: 'up', label: 'up axis (kept per mesh)', options: ['Y', 'Z'] },
  { key: 'chunkSplits', label: 'splits per packet', type: 'number', min: 16, step: 256 },
];

function formatBytes(n) {
  return n < 1024 ? `${n} B` : n < 2 ** 20 ? `${(n / 1024).toFixed(1)} KiB`
    : `${(n / 2 ** 20).toFixed(2)} MiB`;
}

export class Panel {
  // viewer: the bus; root: the panel's element.
  constructor(viewer, root) {
    this.viewer = viewer;
    this.settings = viewer.settings;
    this.root = root;
    const $ = (selector) => root.querySelector(selector);
    this.select = $('#mesh-select');
    this.status = $('#status');
    this.slider = $('#level-slider');
    this.number = $('#level-input');
    this.stats = $('#stats');
    // the mesh shown: its summary, error curve, level held and level moved to
    this.info = this.curve = this.state = this.target = null;
    this.bytes = this.textureBytes = 0;
    this.lastPacket = '';
    this.listTimer = 0;
    this.opening = null;        // the latest open(), so an earlier one stops
    this.listen();
    this.wire($);
    this.setLevelEnabled(false);
    const wanted = new URL(window.location.href).searchParams.get('mesh');
    this.refreshList(wanted).then((meshes) => {
      const listed = meshes.some((mesh) => mesh.id === wanted);
      const first = wanted || meshes.find((mesh) => mesh.status === 'ready')?.id;
      if (first) return this.open(first, { listed: listed || !wanted });
      return null;
    }).catch((error) => { this.status.textContent = `error: ${error.message}`; });
  }

  // ---- meshes ----------------------------------------------------------------

  async listMeshes() {
    const response = await fetch('../meshes?limit=1000');
    if (!response.ok) throw new Error(`listing meshes failed (${response.status})`);
    return (await response.json()).meshes;
  }

  // Lists the server's meshes (keeping `selected`, or the current choice,
  // selected); polls again while one is queued or building.
  async refreshList(selected = this.select.value) {
    const { select } = this;
    clearTimeout(this.listTimer);
    const meshes = await this.listMeshes();
    const prompt = meshes.length ? 'choose a mesh' : 'no meshes: upload one';
    select.replaceChildren(new Option(prompt, ''));
    for (const mesh of meshes) {
      const size = mesh.vertices ? ` · ${mesh.vertices.toLocaleString()} vertices` : '';
      select.append(new Option(`${mesh.name} · ${mesh.status}${size}`, mesh.id));
    }
    select.value = meshes.some((mesh) => mesh.id === selected) ? selected : '';
    if (meshes.some((mesh) => PENDING.has(mesh.status))) {
      this.listTimer = setTimeout(() => this.refreshList().catch(() => {}), LIST_REFRESH_MS);
    }
    return meshes;
  }

  // Whether the server knows mesh `id` (a 404 or 422: it does not).
  async known(id) {
    const response = await fetch(`../meshes/${encodeURIComponent(id)}`);
    if (response.ok) return true;
    if (response.status === 404 || response.status === 422) return false;
    throw new Error(`looking the mesh up failed (${response.status})`);
  }

  async open(id, { listed = false } = {}) {
    const ticket = this.opening = {};
    this.setLevelEnabled(false);
    if (!listed && !(await this.known(id))) {
      if (this.opening !== ticket) return;
      const url = new URL(window.location.href);
      url.searchParams.delete('mesh');
      window.history.replaceState(null, '', url);
      this.select.value = '';
      // (an id is letters, digits, - and _: anything else is not repeated back)
      this.status.textContent = /^[\w-]{1,64}$/.test(id)
        ? `there is no mesh with the id "${id}"; choose one from the list`
        : 'the link names no mesh id; choose a mesh from the list';
      return;
    }
    if (this.opening !== ticket) return;
    const url = new URL(window.location.href);
    if (url.searchParams.get('mesh') !== id) {
      // another mesh: the level and camera kept in the URL were that mesh's
      for (const key of ['level', 'camera']) url.searchParams.delete(key);
    }
    url.searchParams.set('mesh', id);
    window.history.replaceState(null, '', url);
    this.select.value = id;
    [this.info, this.state, this.textureBytes] = [null, null, 0];
    this.stats.replaceChildren();
    this.viewer.emit('open', { id });
  }

  // ---- the level ---------------------------------------------------------------

  levelOf(position) {
    const { base_vertices: base, vertices: full } = this.info;
    return Math.round(base * (full / base) ** (position / SLIDER_STEPS));
  }

  positionOf(level) {
    const { base_vertices: base, vertices: full } = this.info;
    return full === base ? 0 : SLIDER_STEPS * Math.log(level / base) / Math.log(full / base);
  }

  // A level asked for by hand: it ends the automatic choice.
  request(level) {
    if (!this.info) return;
    if (this.settings.autoByDistance) this.change('autoByDistance', false);
    this.viewer.emit('goto', level);
  }

  onKey(event) {
    const { info, target } = this;
    const focus = event.target;
    // Level keys over the closed mesh dropdown move the level, not the choice of
    // mesh (the browser would open each mesh in turn); Alt+Down or Space opens it.
    const onSelect = focus === this.select;
    const typing = !onSelect && focus.matches?.('input:not([type=range]), select, textarea');
    if (typing || event.ctrlKey || event.metaKey || event.altKey) return;
    const levelKey = event.key in KEY_STEPS || event.key === 'Home' || event.key === 'End';
    if (onSelect && levelKey) event.preventDefault();
    if (!info) return;
    let level = null;
    if (event.key === 'Home') level = info.base_vertices;
    else if (event.key === 'End') level = info.vertices;
    else if (event.key in KEY_STEPS) {
      const steps = KEY_STEPS[event.key];
      // Shift: one split or collapse at a time
      level = event.shiftKey ? target + Math.sign(steps)
                             : this.levelOf(Math.round(this.positionOf(target)) + steps);
      if (level === target) level += Math.sign(steps);   // always move at least one level
    }
    if (level === null) return;
    event.preventDefault();
    this.request(level);
  }

  // ---- settings ----------------------------------------------------------------

  change(key, value) {
    this.settings[key] = value;
    this.showSetting(key);
    this.viewer.emit('settings', key);
  }

  // The control of setting `key` shows its value.
  showSetting(key) {
    const input = this.root.querySelector(`[data-key="${key}"]`);
    if (!input) return;
    if (input.type === 'checkbox') input.checked = this.settings[key];
    else input.value = this.settings[key];
  }

  setLevelEnabled(enabled) {
    this.slider.disabled = this.number.disabled = !enabled;
  }

  makeControl({ key, label, type, options, min, step }) {
    const { settings } = this;
    const row = document.createElement('label');
    let input;
    if (options) {
      input = document.createElement('select');
      input.append(...options.map((option) => new Option(option, option)));
    } else {
      input = Object.assign(document.createElement('input'), { type });
      if (min !== undefined) Object.assign(input, { min, step });
    }
    input.dataset.key = key;
    if (type === 'checkbox') input.checked = settings[key];
    else input.value = settings[key];
    input.addEventListener('change', () => {
      const value = type === 'checkbox' ? input.checked
        : type === 'number' ? Number(input.value) : input.value;
      if (type === 'number' && !(value >= min)) input.value = settings[key];
      else this.change(key, value);
    });
    row.append(input, ` ${label}`);
    return row;
  }

  // ---- stats -------------------------------------------------------------------

  showStats() {
    const { state, curve, info, target, settings, bytes, textureBytes } = this;
    if (!state) return;
    const error = curve.errorAt(state.level);
    const rows = [
      ['vertices', `${state.level.toLocaleString()} / ${info.vertices.toLocaleString()}`],
      ['detail', settings.autoByDistance ? `${settings.errorBudgetPx} px`
        : target === info.vertices ? 'full detail' : 'set by hand'],
      ['faces', `${state.faceCount.toLocaleString()} / ${info.faces.toLocaleString()}`],
      ['error', error === 0 ? '0'
        : `${curve.isExact(state.level) ? '' : '≈ '}${error.toPrecision(3)} mesh units`],
      ['received', textureBytes
        ? `${formatBytes(bytes + textureBytes)} (textures ${formatBytes(textureBytes)})`
        : formatBytes(bytes)],
      ['last packet', this.lastPacket],
    ];
    if (target !== state.level) rows[0][1] += ` → ${target.toLocaleString()}`;
    this.stats.replaceChildren();
    for (const [name, value] of rows) {
      const row = this.stats.insertRow();
      row.insertCell().textContent = name;
      row.insertCell().textContent = value;
    }
  }

  // ---- wiring ------------------------------------------------------------------

  // The viewer's signals the panel shows.
  listen() {
    const { viewer } = this;
    viewer.on('mesh', (detail) => {
      ({ info: this.info, curve: this.curve, state: this.state } = detail);
      const { info } = this;
      this.target = this.state.level;
      this.setLevelEnabled(info.vertices !== info.base_vertices);
      this.showSetting('up');                 // chosen for this mesh as it opened
      // the list may still say "queued" or "building" for the mesh now shown
      const option = [...this.select.options].find((each) => each.value === info.id);
      if (option && !option.textContent.includes(' · ready')) {
        this.refreshList(info.id).catch(() => {});
      }
      Object.assign(this.number, { min: info.base_vertices, max: info.vertices });
      this.showStats();
    });
    viewer.on('level', (detail) => {
      ({ state: this.state, bytes: this.bytes } = detail);
      if (detail.records) {
        this.lastPacket = `${detail.records.toLocaleString()} records applied in ` +
                          `${detail.applyMs.toFixed(1)} ms`;
      }
      this.showStats();
    });
    viewer.on('target', (level) => {
      this.target = level;
      this.slider.value = this.positionOf(level);
      this.number.value = level;
      this.showStats();
    });
    viewer.on('status', (text) => { this.status.textContent = text; });
    viewer.on('textures', (received) => {
      this.textureBytes = received;
      this.showStats();
    });
    // settings changed elsewhere (the up axis chosen for a mesh): show them
    viewer.on('settings', (key) => {
      this.showStats();
      this.showSetting(key);
    });
    // an upload (upload.js) the server accepted: list it and open it
    viewer.on('uploaded', (id) => {
      this.refreshList(id).then(() => this.open(id, { listed: true })).catch((error) => {
        this.status.textContent = `error: ${error.message}`;
      });
    });
  }

  // The panel's controls.
  wire($) {
    const { select, slider, number } = this;
    select.addEventListener('change', () => select.value && this.open(select.value, { listed: true }));
    // opening the dropdown shows fresh statuses
    select.addEventListener('pointerdown', () => { this.refreshList().catch(() => {}); });
    // full detail, one click away from the budget's level
    $('#full-detail').addEventListener('click', () => this.info && this.request(this.info.vertices));
    slider.max = SLIDER_STEPS;
    slider.addEventListener('input', () => this.request(this.levelOf(Number(slider.value))));
    number.addEventListener('change', () => {
      // an emptied or unreadable box means no new level: show the current one again
      const value = number.value.trim() === '' ? NaN : Number(number.value);
      if (Number.isFinite(value)) this.request(value);
      else number.value = this.target ?? '';
    });
    window.addEventListener('keydown', (event) => this.onKey(event));
    $('#settings').append(...CONTROLS.map((control) => this.makeControl(control)));
  }
}
