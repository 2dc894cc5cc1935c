// The page's state and the types of what the service sends (app/api/routes/state.py,
// strep_core/runview.py: the server reduces every job; the page only draws).

/**
 * @typedef {[number, number]} Point
 * @typedef {object} RunView  One run as the server reduced it (strep_core.runview.RunView).
 * @property {string | null} method
 * @property {boolean} learned
 * @property {string} unit
 * @property {"iterations" | "frames"} axis  what the curves' x counts
 * @property {number} done
 * @property {number} total
 * @property {string} progress
 * @property {string | null} stage
 * @property {string} stage_text
 * @property {Point[]} loss
 * @property {Point[]} ate
 * @property {Point | null} ate_start
 * @property {Point | null} ate_end
 * @property {number | null} ate_now
 * @property {number | null} point_l2
 * @property {number | null} seconds
 * @property {boolean} finished
 *
 * @typedef {"queued" | "running" | "succeeded" | "failed" | "cancelled" | "interrupted"} JobStatus
 * @typedef {object} JobState  A job as the page shows it (JobStatePublic).
 * @property {string} id
 * @property {JobStatus} status
 * @property {string | null} error
 * @property {string} sequence_id
 * @property {string | null} comparison_id
 * @property {string[]} files
 * @property {RunView} run
 *
 * @typedef {object} Job  A job record (JobPublic), as far as the page reads it.
 * @property {string} id
 * @property {JobStatus} status
 * @property {string} method
 * @property {string} sequence_id
 * @property {string | null} comparison_id
 * @property {string} created_at
 * @property {string | null} error
 * @property {Record<string, unknown> | null} metrics
 *
 * @typedef {object} Comparison  (ComparisonPublic)
 * @property {string} id
 * @property {string} sequence_id
 * @property {string[]} methods
 * @property {JobStatus} status
 * @property {Job[]} jobs
 * @property {string[]} files
 *
 * @typedef {object} Sequence  (SequencePublic)
 * @property {string} id
 * @property {string} name
 * @property {"upload" | "sample"} source
 * @property {number} frames
 * @property {number} dims
 * @property {number} points
 * @property {string | null} unit
 * @property {boolean | null} has_ground_truth
 *
 * @typedef {object} Method  (MethodPublic)
 * @property {string} name
 * @property {string} description
 * @property {boolean} learned
 *
 * @typedef {object} Start  (StartPublic)
 * @property {string} name
 * @property {string} label
 * @property {string} description
 * @property {number} iterations
 *
 * @typedef {object} Preset  The comparison the page offers first (PresetPublic).
 * @property {string} sequence_id
 * @property {string[]} methods
 * @property {string} start
 *
 * @typedef {object} Followed  A followed job: its colour and its latest state.
 * @property {string} id
 * @property {string} method
 * @property {string} color
 * @property {JobState | null} state
 */

/** Curve colours, in the order the methods were chosen. */
export const COLORS = ["#2f6fde", "#e67e22", "#27ae60", "#8e44ad", "#c0392b", "#16a085", "#7f8c8d"];
export const FINAL = new Set(["succeeded", "failed", "cancelled", "interrupted"]);

export const state = {
  /** @type {Followed[]} the live panel's jobs, in the comparison's order */
  followed: [],
  /** @type {string | null} */
  comparison: null,
  /** @type {string[]} */
  comparisonFiles: [],
  /** @type {string | null} the comparison this page started (its end is announced) */
  started: null,
  /** @type {Sequence[]} */
  sequences: [],
  /** @type {Method[]} */
  methods: [],
  /** @type {Start[]} */
  starts: [],
  /** @type {Preset | null} */
  preset: null,
  /** @type {string | null} the 3D viewer's address */
  viewer: null,
  /** bumps whenever the live panel shows another comparison (old streams then stop) */
  generation: 0,
};

/**
 * A sequence's name (an upload's file name, a sample's name); its id when it is gone.
 * @param {string} id
 * @returns {string}
 */
export function sequenceName(id) {
  return state.sequences.find((s) => s.id === id)?.name ?? id;
}

/** @returns {JobState[]} the followed jobs' states that have arrived */
export function followedStates() {
  return state.followed.flatMap((f) => (f.state ? [f.state] : []));
}
