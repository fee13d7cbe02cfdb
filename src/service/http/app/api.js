// Requests to the API: the key (kept in sessionStorage, sent as the bearer token the API
// takes), problem+json answers turned into errors, and a job's event stream.

const KEY = "photostereo-api-key";

export const getKey = () => sessionStorage.getItem(KEY) || "";
export const setKey = (k) => (k ? sessionStorage.setItem(KEY, k) : sessionStorage.removeItem(KEY));

export class ApiProblem extends Error {
  constructor(problem, status) {
    super(problem.detail || problem.title);
    this.problem = problem.type ? problem : null;
    this.title = problem.title || `HTTP ${status}`;
    this.detail = problem.detail || "";
    this.status = status;
  }
}

function headers() {
  const k = getKey();
  return k ? { Authorization: `Bearer ${k}` } : {};
}

// The response, or an ApiProblem for an error status.
async function raw(method, path, body, signal) {
  let r;
  try {
    r = await fetch(path, { method, body, headers: headers(), signal });
  } catch (e) {
    if (e.name === "AbortError") throw e;
    throw new ApiProblem({ title: "The server does not answer", detail: String(e.message || e) }, 0);
  }
  if (r.ok || r.status === 304) return r;
  let problem = { title: `HTTP ${r.status}`, detail: r.statusText };
  if ((r.headers.get("content-type") || "").includes("json")) {
    try {
      problem = await r.json();
    } catch {
      // keep the status line
    }
  }
  throw new ApiProblem(problem, r.status);
}

// JSON of the answer (null for 204).
export async function api(method, path, body) {
  const r = await raw(method, path, body);
  return r.status === 204 ? null : r.json();
}
api.raw = raw;

// Follow a job: `onJob(view)` for each change, `onJob(null)` once it is gone. Reads
// GET /v1/jobs/{id}/events with fetch (EventSource cannot send the API key); when the
// stream cannot be had, polls the job instead. Returns a function that stops following.
export function followJob(id, onJob) {
  const stop = new AbortController();
  let finished = false;
  const done = (job) => {
    if (job === null || ["succeeded", "failed", "cancelled"].includes(job.status)) finished = true;
    onJob(job);
  };
  (async () => {
    try {
      await stream(`/v1/jobs/${id}/events`, stop.signal, (name, data) => {
        if (name === "deleted") done(null);
        else if (name === "job") done(JSON.parse(data));
      });
    } catch (e) {
      if (e.name === "AbortError") return;
      if (e.status === 404) return done(null);
    }
    // The stream ended early (a restart, a proxy): poll until the job is finished.
    while (!finished && !stop.signal.aborted) {
      await new Promise((ok) => setTimeout(ok, 1500));
      if (stop.signal.aborted) return;
      try {
        done(await api("GET", `/v1/jobs/${id}`));
      } catch (e) {
        if (e.status === 404) done(null);
      }
    }
  })();
  return () => stop.abort();
}

// Read a text/event-stream body, calling onEvent(name, data) per event.
async function stream(path, signal, onEvent) {
  const r = await raw("GET", path, undefined, signal);
  const reader = r.body.pipeThrough(new TextDecoderStream()).getReader();
  let buf = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buf += value.replace(/\r\n?/g, "\n");
    let end;
    while ((end = buf.indexOf("\n\n")) >= 0) {
      const block = buf.slice(0, end);
      buf = buf.slice(end + 2);
      let name = "message";
      const data = [];
      for (const line of block.split("\n")) {
        if (line.startsWith("event:")) name = line.slice(6).trim();
        else if (line.startsWith("data:")) data.push(line.slice(5).replace(/^ /, ""));
      }
      if (data.length) onEvent(name, data.join("\n"));
    }
  }
}
