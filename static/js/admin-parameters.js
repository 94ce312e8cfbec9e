// How the model page names a fitted model's parameters (two states, or K ≥ 3 with state 0 the lowest trust)
// and their statuses.

export const STATUS_TEXT = {
  estimated: "estimated",
  boundary: "at a bound",
  unidentified: "not identified",
  not_exercised: "not exercised",
};
export const STATUS_LEGEND = "SE: Laplace standard error. At a bound: the estimate is 0 or 1, where the Laplace approximation "
  + "gives no standard error. Not identified: the data cannot tell this value apart from others (a flat likelihood). "
  + "Not exercised: no trial of the data had these inputs.";

/** "P(trust high next | trust low, high complexity, robot auto, negative experience)" for a parameter name (of a
 * model of K ≥ 3 states: state 0 is the lowest trust). */
export function parameterLabel(name) {
  const parts = name.split(".");
  const state = (part) => part.replace(/^(from_|to_|p_rely_)?state_/, "state ");
  if (name === "initial.p_high") return "P(trust high at the first trial)";
  if (parts[0] === "initial") return `P(trust in ${state(parts[1])} at the first trial)`;
  if (parts[0] === "transitions" && parts.length === 6) {
    const [, complexity, action, experience, from, to] = parts;
    return `P(trust in ${state(to)} next | trust in ${state(from)}, ${complexity} complexity, robot ${action}, `
      + `${experience} experience)`;
  }
  if (parts[0] === "emissions" && parts[3].startsWith("p_rely_state_")) {
    return `P(rely | trust in ${state(parts[3])}, ${parts[1]} complexity, robot ${parts[2]})`;
  }
  if (parts[0] === "transitions" && parts.length === 5) {
    const [, complexity, action, experience, from] = parts;
    return `P(trust high next | trust ${from.replace("from_", "")}, ${complexity} complexity, robot ${action}, `
      + `${experience} experience)`;
  }
  if (parts[0] === "emissions" && parts.length === 4) {
    return `P(rely | trust ${parts[3].replace("p_rely_", "")}, ${parts[1]} complexity, robot ${parts[2]})`;
  }
  return name;
}
