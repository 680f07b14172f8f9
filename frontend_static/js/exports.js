// Exports are jobs on the server (docs/exports.md "Streaming and jobs"): start one, show its progress,
// then download the file; when it fails, say why on the page (issue 20 defect 11: the browser only saw a
// cancelled download).
import { API, get, post } from "./api.js";
import { h } from "./ui.js";

const POLL_MS = 500;

const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

function describe(job) {
  const megabytes = (job.bytes / 1e6).toFixed(1);
  if (job.state === "queued") return "Waiting for a free export slot…";
  if (job.state === "running") return `Building: ${Math.round(job.fraction * 100)} %, ${megabytes} MB so far…`;
  if (job.state === "done") return `Ready: ${megabytes} MB, downloading ${job.filename}.`;
  return `The export failed: ${job.error}`;
}

// A button that starts the export at `startPath` (a POST …/jobs path with its query), a progress bar and a
// status line that says how far it is, or why it failed.
export function exportControl(label, startPath) {
  const progress = h("progress", { max: 1, value: 0, hidden: true, "aria-label": `${label}: progress` });
  const status = h("span.muted", { role: "status", "aria-live": "polite" });
  const button = h("button.primary", { type: "button" }, label);
  button.addEventListener("click", async () => {
    button.disabled = true;
    progress.hidden = false;
    progress.value = 0;
    status.className = "muted";
    try {
      let job = await post(typeof startPath === "function" ? startPath() : startPath);
      while (job.state === "queued" || job.state === "running") {
        progress.value = job.fraction;
        status.textContent = describe(job);
        await sleep(POLL_MS);
        job = await get(`/exports/jobs/${job.id}`);
      }
      progress.value = job.state === "done" ? 1 : progress.value;
      status.textContent = describe(job);
      if (job.state === "done") {
        const link = h("a", { href: `${API}/exports/jobs/${job.id}/download`, download: job.filename, hidden: true });
        document.body.append(link);
        link.click();
        link.remove();
      } else {
        status.className = "error";
      }
    } catch (error) {
      status.className = "error";
      status.textContent = `The export failed: ${error.message}`;
    } finally {
      button.disabled = false;
    }
  });
  return h("span.row", { dataset: { export: label } }, button, progress, status);
}
