// Growable typed arrays, for the decoder's scratch lists and touched lists.
// The decoder sizes its scratch for a typical record and grows it on the rare
// record that needs more, so the hot loops index plain typed arrays instead of
// pushing to JavaScript arrays. (No part of docs/packets.md: a detail of this
// decoder.)

// A typed array twice as long holding the first `used` items of `array`.
export function grow(array, used) {
  const bigger = new array.constructor(2 * Math.max(array.length, 8));
  bigger.set(array.subarray(0, used));
  return bigger;
}
