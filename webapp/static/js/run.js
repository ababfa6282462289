// run: placeholder, being written.
export function init(_ctx) {}
export async function show(_arg) {}
export const events = {};
