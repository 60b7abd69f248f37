// A signal bus: the settings the parts read, and events they emit and listen to
// (main.js's viewer, and each scene part's own stream in animated.js).
export function createBus(settings) {
  const signals = new EventTarget();
  return {
    settings,
    emit(type, detail) {
      signals.dispatchEvent(new CustomEvent(type, { detail }));
    },
    on(type, listener) {
      signals.addEventListener(type, (event) => listener(event.detail));
    },
  };
}
