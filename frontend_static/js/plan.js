// A booking's motion plan (GET /sessions/{id} `plan`), in words, followed while the robot builds it.
import { get } from "./api.js";

/** The plan's state in words. */
export function planWords(plan) {
  if (!plan) return "not known: the robot does not answer; Start plans and checks it then";
  if (plan.state === "ready") return "ready: checked sample by sample; Start plays it at once";
  if (plan.state === "refused") return `refused by the check: ${plan.reason}`;
  const done = `${Math.round(plan.progress * 100)} %`;
  if (plan.state === "stale") return `out of date (the robot, its settings or the patient changed): planning again, ${done}`;
  return `planning and checking, ${done}`;
}

/** Shows `plan` in `element` and asks again every second while it is being built; returns the stop. */
export function followPlan(sessionId, element, plan) {
  let timer = null;
  const show = (current) => {
    element.textContent = planWords(current);
    element.dataset.state = current ? current.state : "unknown";
    if (current && (current.state === "planning" || current.state === "stale")) {
      timer = setTimeout(() => get(`/sessions/${sessionId}`).then((b) => show(b.plan)).catch(() => show(null)), 1000);
    }
  };
  show(plan);
  return () => clearTimeout(timer);
}
