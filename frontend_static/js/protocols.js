// The protocol library (issue 16, build §6): named programmes a therapist copies to any patient, adapts in
// the prescription editor (with its preview, the robot's own check) and saves as a versioned prescription.
// The numbers are starting points inside the robot's limits, not norms: the therapist sets the dose.
import { get } from "./api.js";
import { field, fmt, h } from "./ui.js";

const sine = (axis, amplitude, frequency, duration) => ({ cue: { kind: "sine", axis, amplitude_m_s2: amplitude, frequency_hz: frequency }, duration_s: duration });
const quiet = (duration) => sine("x", 0, 0.1, duration); // a still platform: the condition is in the instruction

export const PROTOCOLS = [
  {
    key: "progressive-lateral-sway",
    name: "Progressive lateral sway",
    purpose: "Weight shifting from one foot to the other, growing in four steps of one minute.",
    instructions: "Stand naturally, eyes open, hands free of the rails. Stop early if the patient grabs or steps.",
    segments: [0.3, 0.45, 0.6, 0.75].map((amplitude) => sine("y", amplitude, 0.25, 60)),
  },
  {
    key: "perturbation-levels",
    name: "Perturbation levels",
    purpose: "Unannounced forward–back pulses at three levels, for reactive balance (ankle and hip strategies).",
    instructions: "Tell the patient that pushes will come at random moments; the harness is attached throughout.",
    segments: [0.5, 1.0, 1.5].map((level) => ({
      cue: { kind: "perturbations", translation_m_s2: level, pulse_duration_s: 0.5, interval_min_s: 4, interval_max_s: 8 }, duration_s: 90 })),
  },
  {
    key: "gait-like",
    name: "Gait-like work",
    purpose: "The rhythm of walking under the feet: vertical and fore–aft at the step rate, lateral at the stride rate.",
    instructions: "Let the patient march on the spot with the platforms, or stand and follow the weight shifts.",
    segments: [80, 100].map((cadence) => ({
      cue: { kind: "gait", cadence_steps_per_min: cadence, lateral_amplitude_m_s2: 0.4, forward_amplitude_m_s2: 0.3, vertical_amplitude_m_s2: 0.2 },
      duration_s: 120 })),
  },
  {
    key: "sensory-organisation-sequence",
    name: "Sensory-organisation-style sequence",
    purpose: "Six 20-second conditions in the order of a sensory organisation test: still support with eyes open and closed, then a slowly tilting support with eyes open and closed, then side to side.",
    instructions: "Conditions 1, 3 and 5 with eyes open, 2, 4 and 6 with eyes closed (tell the patient at each change). The tilting support is slow pitch, not the sway-referenced support of a clinical test.",
    segments: [quiet(20), quiet(20),
      { cue: { kind: "sine", axis: "pitch", amplitude_rad_s: 0.03, frequency_hz: 0.1 }, duration_s: 20 },
      { cue: { kind: "sine", axis: "pitch", amplitude_rad_s: 0.03, frequency_hz: 0.1 }, duration_s: 20 },
      sine("y", 0.3, 0.2, 20), sine("y", 0.3, 0.2, 20)],
  },
];

export function protocolByKey(key) {
  const protocol = PROTOCOLS.find((p) => p.key === key);
  if (!protocol) throw new Error(`no protocol “${key}” in the library`);
  return protocol;
}

const totalS = (segments) => segments.reduce((sum, s) => sum + s.duration_s, 0);

export async function protocolsPage(main, params) {
  const patients = await get("/patients?limit=500");
  main.append(h("h1", {}, "Protocol library"),
    h("p", {}, "Copy a programme to a patient: it opens in the prescription editor, where you adapt it, preview it through the robot's own check and save it as the patient's prescription (version 1; later changes make new versions)."));
  for (const protocol of PROTOCOLS) {
    const patient = h("select", { "aria-label": `Patient for ${protocol.name}` },
      h("option", { value: "", disabled: true, selected: !params.get("patient") }, "Choose a patient…"),
      patients.map((p) => h("option", { value: p.id, selected: String(p.id) === params.get("patient") }, `${p.name} (${p.identifier})`)));
    const copy = h("button.primary", { type: "button", disabled: !params.get("patient"),
      onclick: () => { location.hash = `#/prescriptions/new?patient=${patient.value}&protocol=${protocol.key}`; } }, `Copy “${protocol.name}” to the patient`);
    patient.addEventListener("change", () => { copy.disabled = !patient.value; });
    main.append(h("section.panel.protocol", { dataset: { protocol: protocol.key }, "aria-label": protocol.name },
      h("h2", {}, protocol.name), h("p", {}, protocol.purpose), h("p.muted", {}, protocol.instructions),
      h("p", {}, `${protocol.segments.length} segments, ${fmt(totalS(protocol.segments) / 60, "min", 1)} of motion.`),
      h("div.row", {}, h("div.grow", {}, field("Patient", patient)), copy)));
  }
}
