// Getting meshes in: one upload of one or several files (a mesh with the files
// it names: an OBJ with its .mtl and textures, a .gltf with its .bin and
// images) or of one .zip of them, picked with a button (keyboard-reachable)
// or dropped onto the view. While the body goes up its bytes are shown (the
// XMLHttpRequest upload's progress events: fetch cannot report them); once
// the server accepted it, its place in the build queue and the build's
// progress, until it is ready. What the load left out (a material library
// named but not sent) is listed; a refusal shows the server's sentence and a
// suggestion of what to send instead.
//
// While a mesh is opened and not yet shown (an upload queued or building, or
// a base level on its way) the view is marked stale: the model of the mesh
// shown before is hidden, so it is never taken for the new one.
//
// Signals out: 'uploaded' (the new mesh's id: ui.js lists and opens it).
// In: 'open' (the view goes stale), 'mesh' or 'scene-shown' (a mesh or a
// scene is shown: fresh again).

const POLL_MS = 500;
const MESH_TYPES = ['obj', 'ply', 'stl', 'off', 'gltf', 'glb'];

function formatBytes(n) {
  return n < 1024 ? `${n} B` : n < 2 ** 20 ? `${(n / 1024).toFixed(1)} KiB`
    : `${(n / 2 ** 20).toFixed(1)} MiB`;
}

function extension(name) {
  const dot = name.lastIndexOf('.');
  return dot < 0 ? '' : name.slice(dot + 1).toLowerCase();
}

// What to do about a refused upload, from its HTTP status and the server's sentence.
export function suggestionFor(status, message = '') {
  const m = message.toLowerCase();
  if (status === 0) return 'check the connection to the server and try again';
  if (status === 401) return 'this server needs its token for uploads';
  if (status === 413) {
    return m.includes('memory') || m.includes('triangles')
      ? 'the mesh is larger than this server builds: upload a simplified copy'
      : 'the upload is larger than this server accepts: send fewer or smaller files';
  }
  if (status === 415) {
    return `choose a mesh file (${MESH_TYPES.map((t) => `.${t}`).join(', ')}), with the ` +
           'files it names, or one .zip of them';
  }
  if (status === 503) return 'the server is busy: try again in a few seconds';
  if (status === 507) return 'the server is out of disk space: try again later';
  if (m.includes("field 'main'")) {
    return 'the files hold several meshes: choose the one to build below, or upload each ' +
           'mesh with its own files';
  }
  if (m.includes('missing')) {
    if (m.includes('buffer')) return 'include the .bin file named in the .gltf in the same upload';
    if (m.includes('material library')) return 'include the .mtl file the .obj names';
    if (m.includes('texture') || m.includes('image')) {
      return 'include the image files the mesh names in the same upload';
    }
    return 'include every file the mesh names in the same upload (select them together, ' +
           'or drop a .zip of them)';
  }
  if (m.includes('leads out') || m.includes('absolute path') || m.includes('symbolic link')) {
    return 'the mesh names a file outside the upload: put the files it names beside it ' +
           '(or in the .zip) and name them by relative paths';
  }
  if (m.includes('zip') || m.includes('archive')) {
    return 'make the .zip again with a standard tool (no links, no encryption)';
  }
  return 'check that the file opens in another program; the message says what is wrong';
}

export class Upload {
  // viewer: the bus; panel: the panel's element (its upload controls);
  // viewport: the view files are dropped on; note: the note over a stale view.
  constructor(viewer, { panel, viewport, note }) {
    this.viewer = viewer;
    this.viewport = viewport;
    this.note = note;
    const $ = (selector) => panel.querySelector(selector);
    this.button = $('#upload-button');
    this.input = $('#upload');
    this.bar = $('#upload-progress');
    this.text = $('#upload-status');
    this.warningList = $('#upload-warnings');
    this.choices = $('#upload-choices');
    this.current = 0;           // counts uploads, so a poll of an earlier one stops
    this.wire();
  }

  say(message, { error = false } = {}) {
    this.text.textContent = message;
    this.text.classList.toggle('error', error);
  }

  showProgress(value) {
    this.bar.hidden = value === null;
    if (value !== null) this.bar.value = value;
  }

  showWarnings(warnings = []) {
    this.warningList.replaceChildren(...warnings.map((warning) => {
      const item = document.createElement('li');
      item.textContent = warning;
      return item;
    }));
  }

  fail(status, message) {
    this.showProgress(null);
    this.say(`upload refused: ${message} — ${suggestionFor(status, message)}`, { error: true });
  }

  // Several mesh files in one upload: a button per mesh file sends the same
  // files again with that one as the form field 'main'.
  offerChoices(files) {
    const meshes = files.filter((file) => MESH_TYPES.includes(extension(file.name)));
    this.choices.replaceChildren(...meshes.map((file) => {
      const choice = document.createElement('button');
      choice.type = 'button';
      choice.textContent = `build ${file.name}`;
      choice.addEventListener('click', () => this.run(files, file.name));
      return choice;
    }));
  }

  // POST /meshes with XMLHttpRequest, for its upload progress events.
  send(files, main, ticket) {
    const form = new FormData();
    for (const file of files) form.append('file', file, file.name);
    if (main) form.append('main', main);
    const total = files.reduce((n, file) => n + file.size, 0);
    const what = files.length === 1 ? files[0].name : `${files.length} files`;
    return new Promise((resolve) => {
      const request = new XMLHttpRequest();
      request.open('POST', '../meshes');
      request.responseType = 'json';
      request.upload.addEventListener('progress', (event) => {
        if (ticket !== this.current) return;
        const sent = event.loaded, length = event.lengthComputable ? event.total : total;
        this.showProgress(length ? sent / length : null);
        this.say(`uploading ${what}: ${formatBytes(Math.min(sent, length))} of ` +
                 `${formatBytes(length)} (${Math.round(100 * sent / Math.max(length, 1))}%)`);
      });
      request.upload.addEventListener('load', () => {
        if (ticket === this.current) this.say(`${what} sent; the server is checking it`);
      });
      request.addEventListener('load', () => resolve({ status: request.status,
                                                        body: request.response || {} }));
      request.addEventListener('error', () => resolve({ status: 0, body: {
        message: 'the connection to the server failed during the upload' } }));
      request.send(form);
    });
  }

  // Queue position and build progress of an accepted upload, until it settles.
  async follow(id, ticket) {
    for (;;) {
      const response = await fetch(`../meshes/${encodeURIComponent(id)}`);
      if (ticket !== this.current) return;
      const body = await response.json().catch(() => ({}));
      if (!response.ok) {
        this.fail(response.status, body.message || `the server answered ${response.status}`);
        return;
      }
      if (body.status === 'ready') {
        this.showProgress(null);
        this.say(`${body.name}: built`);
        if (body.warnings?.length) this.showWarnings(body.warnings);
        return;
      }
      if (body.status === 'failed') {
        this.fail(422, `the build failed: ${body.failure}`);
        return;
      }
      let line;
      if (body.status === 'queued') {
        const ahead = body.queue_position;
        line = ahead == null ? `${body.name}: queued`
          : ahead === 0 ? `${body.name}: queued, next to be built`
          : `${body.name}: queued, ${ahead} upload${ahead === 1 ? '' : 's'} ahead`;
        this.showProgress(0);
      } else {
        line = `${body.name}: building ${Math.round(100 * body.progress)}%`;
        this.showProgress(body.progress);
      }
      this.say(line);
      this.note.textContent = line;
      await new Promise((resolve) => setTimeout(resolve, POLL_MS));
    }
  }

  async upload(list, main = null) {
    const files = [...list];
    if (!files.length) return;
    const ticket = ++this.current;
    this.showWarnings([]);
    this.choices.replaceChildren();
    const { status, body } = await this.send(files, main, ticket);
    if (ticket !== this.current) return;
    if (status !== 202) {
      this.fail(status, body.message || `the server answered ${status}`);
      if (status === 422 && !main && (body.message || '').includes("field 'main'")) {
        this.offerChoices(files);
      }
      return;
    }
    this.showWarnings(body.warnings);
    this.say(`${body.main ?? files[0].name}: accepted`);
    this.viewer.emit('uploaded', body.id);
    await this.follow(body.id, ticket);
  }

  run(files, main) {
    return this.upload(files, main).catch((error) => this.fail(0, error.message));
  }

  wire() {
    const { button, input, viewport, note, viewer } = this;
    // A real button (focusable, Enter/Space) in front of the hidden file input.
    button.addEventListener('click', () => input.click());
    input.addEventListener('change', () => {
      const files = [...input.files];
      input.value = '';          // the same files may be chosen again
      this.run(files);
    });

    // Drag-and-drop onto the view.
    const carriesFiles = (event) => [...(event.dataTransfer?.types ?? [])].includes('Files');
    viewport.addEventListener('dragenter', (event) => {
      if (!carriesFiles(event)) return;
      event.preventDefault();
      viewport.classList.add('dropping');
    });
    viewport.addEventListener('dragover', (event) => {
      if (!carriesFiles(event)) return;
      event.preventDefault();                // without it the browser opens the file
      event.dataTransfer.dropEffect = 'copy';
    });
    viewport.addEventListener('dragleave', (event) => {
      if (!viewport.contains(event.relatedTarget)) viewport.classList.remove('dropping');
    });
    viewport.addEventListener('drop', (event) => {
      event.preventDefault();
      viewport.classList.remove('dropping');
      this.run(event.dataTransfer?.files ?? []);
    });

    // Files dropped anywhere else must not make the browser navigate to them.
    for (const type of ['dragover', 'drop']) {
      window.addEventListener(type, (event) => {
        if (carriesFiles(event) && !viewport.contains(event.target)) event.preventDefault();
      });
    }

    // The view is stale from the moment another mesh is opened until it is shown.
    viewer.on('open', () => {
      viewport.classList.add('stale');
      note.hidden = false;
      note.textContent = 'loading the mesh…';
    });
    const fresh = () => {
      viewport.classList.remove('stale');
      note.hidden = true;
    };
    viewer.on('mesh', fresh);
    viewer.on('scene-shown', fresh);      // a scene (animated.js)
  }
}
