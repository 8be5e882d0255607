// The manual's ramp formulas (sections 1.9 and 1.10), for showing the ramp
// time while the user types. The daemon solves and checks the same formulas
// (src/drive/units.rs); these only preview.

/** Formula (2): speed ramp time from standstill to `rpm`, s. */
export function speedRampTime(alpha, rpm, gearRatio) {
  if (!(alpha > 0) || !(gearRatio > 0)) return null;
  return 2 * Math.sqrt((gearRatio * Math.abs(rpm)) / (9.55 * alpha));
}

/** Formula (2) solved for alpha. */
export function speedRampAlpha(seconds, rpm, gearRatio) {
  if (!(seconds > 0)) return null;
  return Math.round((4 * gearRatio * Math.abs(rpm)) / (9.55 * seconds * seconds));
}

/** Formula (3): position ramp time from standstill through `degrees`, s. */
export function positionRampTime(alpha, degrees) {
  if (!(alpha > 0)) return null;
  return 2 * Math.sqrt((Math.PI * Math.abs(degrees)) / (180 * alpha));
}

/** Formula (3) solved for alpha. */
export function positionRampAlpha(seconds, degrees) {
  if (!(seconds > 0)) return null;
  return Math.round((4 * Math.PI * Math.abs(degrees)) / (180 * seconds * seconds));
}
