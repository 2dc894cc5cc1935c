// Live state: each followed job's snapshots from GET /api/jobs/{id}/state (Server-Sent Events).
// Every message is the job's whole state, reduced by the server: the page keeps the latest.

import { readEvents } from "./api.js";
import { FINAL, state } from "./state.js";

/**
 * Follow one job until it ends (reconnecting after a dropped stream), calling `onState` with
 * each snapshot; stops early when the live panel moves to another comparison.
 * @param {import("./state.js").Followed} entry
 * @param {() => void} onState
 * @returns {Promise<void>}
 */
export async function followJob(entry, onState) {
  const generation = state.generation;
  while (generation === state.generation) {
    try {
      await readEvents(`/api/jobs/${entry.id}/state`, (kind, data) => {
        if (kind !== "state" || generation !== state.generation) return;
        entry.state = JSON.parse(data);
        onState();
      });
    } catch (err) {
      console.warn(err);
    }
    if (entry.state && FINAL.has(entry.state.status)) return;
    await new Promise((r) => setTimeout(r, 1e3)); // a reconnection starts with the whole state
  }
}
