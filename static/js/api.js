// The service's REST API: one fetch wrapper (with the bearer token when the page has one) and
// downloads that send the token. Every name of a file, stage or default comes from the service.

const fromUrl = new URLSearchParams(location.search).get("token");
/** The bearer token (from ?token=, kept for this tab), or null when the service has none. */
export const token = fromUrl || sessionStorage.getItem("strep-token");
if (token) sessionStorage.setItem("strep-token", token);

/**
 * Request headers with the token added.
 * @param {Record<string, string>} [extra]
 * @returns {Record<string, string>}
 */
export function headers(extra = {}) {
  return token ? { ...extra, Authorization: `Bearer ${token}` } : extra;
}

/**
 * Call the API; the JSON (or text) answer, or an Error with the service's `detail`.
 * @template T
 * @param {string} path
 * @param {RequestInit & {headers?: Record<string, string>}} [options]
 * @returns {Promise<T>}
 */
export async function api(path, options = {}) {
  const res = await fetch(path, { ...options, headers: headers(options.headers || {}) });
  const body = res.headers.get("content-type")?.includes("json") ? await res.json() : await res.text();
  if (!res.ok) throw new Error((body && body.detail) || `${res.status} ${res.statusText}`);
  return body;
}

/**
 * Read a Server-Sent Events stream over fetch (so the token header can be sent); calls
 * `onMessage(kind, data)` per message and resolves when the stream ends.
 * @param {string} path
 * @param {(kind: string, data: string) => void} onMessage
 * @returns {Promise<void>}
 */
export async function readEvents(path, onMessage) {
  const res = await fetch(path, { headers: headers() });
  if (!res.ok || !res.body) throw new Error(`${path}: ${res.status}`);
  const reader = res.body.getReader();
  const decoder = new TextDecoder();
  let buf = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) break;
    buf += decoder.decode(value, { stream: true });
    let cut;
    while ((cut = buf.indexOf("\n\n")) >= 0) {
      const block = buf.slice(0, cut);
      buf = buf.slice(cut + 2);
      let kind = "message";
      /** @type {string[]} */
      const data = [];
      for (const line of block.split("\n")) {
        if (line.startsWith("event:")) kind = line.slice(6).trim();
        else if (line.startsWith("data:")) data.push(line.slice(5).replace(/^ /, ""));
      }
      if (data.length) onMessage(kind, data.join("\n"));
    }
  }
}

/**
 * Is this link a download from the API (which needs the token when there is one)?
 * @param {HTMLAnchorElement | null | undefined} link
 * @returns {link is HTMLAnchorElement}
 */
export function isApiDownload(link) {
  return Boolean(link) && new URL(/** @type {HTMLAnchorElement} */ (link).href, location.href).pathname.startsWith("/api/");
}

// A link cannot send the token: with one, the file is fetched with the Authorization header and
// saved from a blob URL, under the name the server gives (Content-Disposition). The token never
// goes into a URL.
/**
 * @param {HTMLAnchorElement} link
 * @returns {Promise<void>}
 */
export async function download(link) {
  const res = await fetch(link.href, { headers: headers() });
  if (!res.ok) {
    const body = await res.json().catch(() => null);
    throw new Error(`download: ${(body && body.detail) || `${res.status} ${res.statusText}`}`);
  }
  const named = /filename="?([^";]+)"?/.exec(res.headers.get("content-disposition") || "");
  const url = URL.createObjectURL(await res.blob());
  const a = document.createElement("a");
  a.href = url;
  a.download = named ? named[1] : new URL(link.href).pathname.split("/").pop() || "download";
  document.body.appendChild(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 60_000);
}
