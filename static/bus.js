// A signal bus: the settings the parts read, and events they emit and listen to
// (main.js's viewer, and each scene part's own stream in animated.js).
export class Bus {
  // settings: the object the parts read their settings from (kept, not copied).
  constructor(settings) {
    this.settings = settings;
    this.signals = new EventTarget();
  }

  emit(type, detail) {
    this.signals.dispatchEvent(new CustomEvent(type, { detail }));
  }

  // listener(detail) for each signal of `type`.
  on(type, listener) {
    this.signals.addEventListener(type, (event) => listener(event.detail));
  }
}
