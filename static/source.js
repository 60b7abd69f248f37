// Where a progressive mesh's records come from: a lodserver (ServerSource),
// or a progressive file on a static host (staticsource.js: StaticSource). The
// stream (stream.js) asks a source for four things only, so another source
// needs only these:
//   summary          GET /meshes/{id}: counts, error curve, bounds, parts
//   base(level)      the json level packets start from (an ArrayBuffer)
//   packet(from, to) the vertex-split packet between two levels ({ buffer, url }),
//                    or several in a row ({ buffers, url })
//   materials()      the glTF material records ({ document, url }: image uris
//                    are relative to url)
// A source whose levels are fixed (a file's chunk ends) also has snap(level,
// direction), the nearest level it holds, and nextStop(from, to, records),
// where a request of about `records` records stops.
// A failure is a FetchError, `transient` when asking again may help (the
// stream retries those with backoff).

const POLL_MS = 500;
// The packet versions packet.js reads (version 4 through packet_v4.js).
const READ_VERSIONS = [1, 2, 3, 4];

// An HTTP failure: `transient` when asking again may help.
export class FetchError extends Error {
  constructor(message, transient) {
    super(message);
    this.transient = transient;
  }
}

export function sleep(ms, signal) {
  return new Promise((resolve, reject) => {
    const timer = setTimeout(resolve, ms);
    signal?.addEventListener('abort', () => {
      clearTimeout(timer);
      reject(signal.reason);
    }, { once: true });
  });
}

// fetch() whose failures are FetchErrors: a network error, 408, 429 and 5xx
// transient, another status not; an abort stays an AbortError.
export async function fetchOk(url, options) {
  let response;
  try {
    response = await fetch(url, options);
  } catch (error) {
    if (error.name === 'AbortError') throw error;
    throw new FetchError(`the request failed (${error.message})`, true);
  }
  if (!response.ok) {
    const body = await response.json().catch(() => ({}));
    const status = response.status;
    throw new FetchError(body.message || `the server answered ${status}`,
                         status >= 500 || status === 408 || status === 429);
  }
  return response;
}

// Retries: `attempt()` again after a transient FetchError (a network error,
// 408, 429, 5xx; a body cut short), with exponential backoff (RETRY_BASE_MS
// doubling, up to RETRY_MAX_MS), `retries` times; any other failure, an abort
// or giveUp() ends it at once. onRetry({ attempt, delayMs, error }) before each wait.
const RETRY_BASE_MS = 250;
const RETRY_MAX_MS = 8000;

export async function withRetries(attempt, { retries, signal, giveUp = () => false, onRetry }) {
  for (let n = 0; ; n++) {
    try {
      return await attempt();
    } catch (error) {
      if (signal?.aborted || giveUp()) throw error;
      if (!(error instanceof FetchError && error.transient) || n >= retries) throw error;
      const delayMs = Math.min(RETRY_MAX_MS, RETRY_BASE_MS * 2 ** n);
      onRetry({ attempt: n + 1, delayMs, error });
      await sleep(delayMs, signal);
    }
  }
}

// A source whose levels are fixed (a progressive file's chunk ends: its snap())
// holds only those: a level asked for moves to the nearest one past it.
export function snapLevel(source, level, direction = 'up') {
  return source?.snap ? source.snap(level, direction) : level;
}

// The API root the viewer's page is served under (it serves the viewer at
// viewer/): the page's parent, so a path prefix added by a proxy is kept.
export function pageRoot() {
  return new URL('../', window.location.href).href;
}

// The URL of a route of a mesh ('lod', 'splits', 'materials') with
// `params`: at the mesh's version when its summary hands out versioned URLs
// (GET /meshes/{id}: urls, `?v=`; the server marks such responses immutable,
// so any cache keeps them for a year), else unversioned (cached a minute).
// The summary's URLs are rooted at the API (`root`, the page's parent by default).
// A scene's part (GET /meshes/{id}: parts[p].urls) is opened as a mesh whose
// summary has such urls; a URL that is a template ({from}, {to}, ...) has
// its named parameters filled in rather than added.
export function routeUrl(summary, route, params = {}, root = pageRoot()) {
  let versioned = summary.urls?.[route];
  const rest = { ...params };
  if (versioned) {
    versioned = versioned.replace(/\{(\w+)\}/g, (whole, key) => {
      if (!(key in rest)) return '';
      const value = encodeURIComponent(rest[key]);
      delete rest[key];
      return value;
    });
  }
  const url = versioned
    ? new URL(versioned.replace(/^\/+/, ''), root)
    : new URL(`meshes/${encodeURIComponent(summary.id)}/${route}`, root);
  for (const [key, value] of Object.entries(rest)) url.searchParams.set(key, value);
  return url.href;
}

// A mesh URL (http://host/prefix/meshes/ID) split into the API root
// (http://host/prefix/) and the id; a clear error for anything else.
export function parseMeshUrl(url, base = window.location.href) {
  const parsed = new URL(url, base);
  const match = /^(.*\/)meshes\/([^/]+)\/?$/.exec(parsed.pathname);
  if (!match || !/^https?:$/.test(parsed.protocol)) {
    throw new Error(`not a lodserver mesh URL (http://host/meshes/ID): ${url}`);
  }
  return { root: `${parsed.origin}${match[1]}`, id: decodeURIComponent(match[2]) };
}

// A mesh on a lodserver: its routes at the summary's version.
export class ServerSource {
  // summary: GET /meshes/{id} (or a scene part's record with the scene's id);
  // root: the API root its URLs are relative to.
  constructor(summary, root = pageRoot()) {
    this.summary = summary;
    this.root = root;
  }

  // The source of mesh `id` once the server has built it; onProgress(summary)
  // hears each poll while it is queued or building, and stops the wait (null)
  // by returning false; so does `signal`.
  static async open(id, { root = pageRoot(), signal = null, onProgress = null } = {}) {
    const url = new URL(`meshes/${encodeURIComponent(id)}`, root).href;
    for (;;) {
      const summary = await (await fetchOk(url, { signal })).json();
      if (signal?.aborted) return null;
      if (summary.status === 'ready') return new ServerSource(summary, root);
      if (summary.status === 'failed') throw new Error(`the build failed: ${summary.failure}`);
      if (onProgress?.(summary) === false) return null;
      await sleep(POLL_MS, signal);
    }
  }

  url(route, params = {}) {
    return routeUrl(this.summary, route, params, this.root);
  }

  // The source of a scene's part (GET /meshes/{id}: parts[p]).
  part(record) {
    const { id, name } = this.summary;
    return new ServerSource({ ...record, id, name: `${name} (${record.name})` }, this.root);
  }

  async base(level, { signal } = {}) {
    const url = this.url('lod', { vertices: level, format: 'json' });
    return (await fetchOk(url, { signal })).arrayBuffer();
  }

  async packet(from, to, { signal } = {}) {
    const url = this.url('splits', { from, to, ...this.versionParam() });
    const response = await fetchOk(url, { signal });
    try {
      return { buffer: await response.arrayBuffer(), url };
    } catch (error) {
      if (error.name === 'AbortError') throw error;
      throw new FetchError(`the packet was cut short (${error.message})`, true);
    }
  }

  // The newest packet version both the server writes (the summary's
  // packet_versions) and packet.js reads; none for a server that lists none
  // (it writes version 3 only, its default).
  versionParam() {
    const offered = this.summary.packet_versions ?? [];
    const version = Math.max(0, ...offered.filter((v) => READ_VERSIONS.includes(v)));
    return version > 3 ? { version } : {};
  }

  // A scene's GLB at `ratio` of its triangles (ProgressiveScene.load): { buffer, url }.
  async sceneGlb({ ratio, signal } = {}) {
    const url = this.url('lod', { ratio, format: 'glb' });
    return { buffer: await (await fetchOk(url, { signal })).arrayBuffer(), url };
  }

  async materials({ signal } = {}) {
    const response = await fetchOk(this.url('materials'), { signal });
    return { document: await response.json(), url: response.url };
  }
}
