// The panel: pick or upload a mesh, move the level (slider, number, keys),
// read the stats, change the settings.
//
// The slider is logarithmic in the level: a mesh's interesting coarse levels
// span a few hundred vertices, its fine ones hundreds of thousands.
//
// Signals out: 'open' (a mesh id), 'goto' (a level), 'settings' (a key).
// In: 'mesh', 'level', 'target', 'status', 'settings'.

const SLIDER_STEPS = 1000;
const KEY_STEPS = { ArrowUp: 10, ArrowRight: 10, ArrowDown: -10, ArrowLeft: -10,
                    PageUp: 100, PageDown: -100 };
// The settings the panel edits: which key, how it is shown.
const CONTROLS = [
  { key: 'autoByDistance', label: 'auto level by distance', type: 'checkbox' },
  { key: 'errorBudgetPx', label: 'error budget (px)', type: 'number', min: 0.05, step: 0.05 },
  { key: 'shading', label: 'shading', options: ['smooth', 'flat'] },
  { key: 'chunkSplits', label: 'splits per packet', type: 'number', min: 16, step: 256 },
];

export function createUi(viewer, root) {
  const { settings } = viewer;
  const $ = (selector) => root.querySelector(selector);
  const select = $('#mesh-select'), upload = $('#upload'), status = $('#status');
  const slider = $('#level-slider'), number = $('#level-input'), stats = $('#stats');
  let info = null, curve = null, state = null, target = null;
  let bytes = 0, lastPacket = '';

  // ---- meshes ----------------------------------------------------------------

  async function listMeshes() {
    const response = await fetch('../meshes?limit=1000');
    if (!response.ok) throw new Error(`listing meshes failed (${response.status})`);
    return (await response.json()).meshes;
  }

  async function refreshList(selected) {
    const meshes = await listMeshes();
    const prompt = meshes.length ? 'choose a mesh' : 'no meshes: upload one';
    select.replaceChildren(new Option(prompt, ''));
    for (const mesh of meshes) {
      const size = mesh.vertices ? ` · ${mesh.vertices.toLocaleString()} vertices` : '';
      select.append(new Option(`${mesh.name} · ${mesh.status}${size}`, mesh.id));
    }
    if (selected && ![...select.options].some((option) => option.value === selected)) {
      select.append(new Option(selected, selected));
    }
    select.value = selected || '';
    return meshes;
  }

  function open(id) {
    const url = new URL(window.location.href);
    url.searchParams.set('mesh', id);
    window.history.replaceState(null, '', url);
    select.value = id;
    viewer.emit('open', id);
  }

  async function uploadFile(file) {
    const form = new FormData();
    form.append('file', file);
    status.textContent = `uploading ${file.name}`;
    const response = await fetch('../meshes', { method: 'POST', body: form });
    const body = await response.json().catch(() => ({}));
    if (!response.ok) throw new Error(body.message || `the upload failed (${response.status})`);
    await refreshList(body.id);
    open(body.id);
  }

  // ---- the level ---------------------------------------------------------------

  function levelOf(position) {
    const { base_vertices: base, vertices: full } = info;
    return Math.round(base * (full / base) ** (position / SLIDER_STEPS));
  }

  function positionOf(level) {
    const { base_vertices: base, vertices: full } = info;
    return full === base ? 0 : SLIDER_STEPS * Math.log(level / base) / Math.log(full / base);
  }

  // A level asked for by hand: it ends the automatic choice.
  function request(level) {
    if (!info) return;
    if (settings.autoByDistance) change('autoByDistance', false);
    viewer.emit('goto', level);
  }

  function onKey(event) {
    const focus = event.target;
    const typing = focus.matches?.('input:not([type=range]), select, textarea');
    if (!info || typing || event.ctrlKey || event.metaKey || event.altKey) return;
    let level = null;
    if (event.key === 'Home') level = info.base_vertices;
    else if (event.key === 'End') level = info.vertices;
    else if (event.key in KEY_STEPS) {
      const steps = KEY_STEPS[event.key];
      // Shift: one split or collapse at a time
      level = event.shiftKey ? target + Math.sign(steps)
                             : levelOf(Math.round(positionOf(target)) + steps);
      if (level === target) level += Math.sign(steps);   // always move at least one level
    }
    if (level === null) return;
    event.preventDefault();
    request(level);
  }

  // ---- settings ----------------------------------------------------------------

  function change(key, value) {
    settings[key] = value;
    const input = root.querySelector(`[data-key="${key}"]`);
    if (input.type === 'checkbox') input.checked = value;
    else input.value = value;
    viewer.emit('settings', key);
  }

  function makeControl({ key, label, type, options, min, step }) {
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
      else change(key, value);
    });
    row.append(input, ` ${label}`);
    return row;
  }

  // ---- stats -------------------------------------------------------------------

  function formatBytes(n) {
    return n < 1024 ? `${n} B` : n < 2 ** 20 ? `${(n / 1024).toFixed(1)} KiB`
      : `${(n / 2 ** 20).toFixed(2)} MiB`;
  }

  function showStats() {
    if (!state) return;
    const error = curve.errorAt(state.level);
    const rows = [
      ['vertices', `${state.level.toLocaleString()} / ${info.vertices.toLocaleString()}`],
      ['faces', `${state.faceCount.toLocaleString()} / ${info.faces.toLocaleString()}`],
      ['error', error === 0 ? '0'
        : `${curve.isExact(state.level) ? '' : '≈ '}${error.toPrecision(3)} mesh units`],
      ['received', formatBytes(bytes)],
      ['last packet', lastPacket],
    ];
    if (target !== state.level) rows[0][1] += ` → ${target.toLocaleString()}`;
    stats.replaceChildren();
    for (const [name, value] of rows) {
      const row = stats.insertRow();
      row.insertCell().textContent = name;
      row.insertCell().textContent = value;
    }
  }

  // ---- wiring ------------------------------------------------------------------

  viewer.on('mesh', (detail) => {
    ({ info, curve, state } = detail);
    target = state.level;
    slider.disabled = number.disabled = info.vertices === info.base_vertices;
    Object.assign(number, { min: info.base_vertices, max: info.vertices });
    showStats();
  });
  viewer.on('level', (detail) => {
    ({ state, bytes } = detail);
    if (detail.records) {
      lastPacket = `${detail.records.toLocaleString()} records applied in ` +
                   `${detail.applyMs.toFixed(1)} ms`;
    }
    showStats();
  });
  viewer.on('target', (level) => {
    target = level;
    slider.value = positionOf(level);
    number.value = level;
    showStats();
  });
  viewer.on('status', (text) => { status.textContent = text; });

  select.addEventListener('change', () => select.value && open(select.value));
  upload.addEventListener('change', () => {
    if (upload.files.length) uploadFile(upload.files[0]).catch((error) => {
      status.textContent = `error: ${error.message}`;
    });
    upload.value = '';
  });
  slider.max = SLIDER_STEPS;
  slider.addEventListener('input', () => request(levelOf(Number(slider.value))));
  number.addEventListener('change', () => request(Number(number.value)));
  window.addEventListener('keydown', onKey);
  $('#settings').append(...CONTROLS.map(makeControl));

  const wanted = new URL(window.location.href).searchParams.get('mesh');
  refreshList(wanted).then((meshes) => {
    const first = wanted || meshes.find((mesh) => mesh.status === 'ready')?.id;
    if (first) open(first);
  }).catch((error) => { status.textContent = `error: ${error.message}`; });
}
