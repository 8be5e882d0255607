// drivegate's alarms as the page reads them: GET /api/v1/alarms (date and
// time, drive, kind, text, what to do, active or cleared, who
// acknowledged it and when).

import { ApiError, get } from './api.js';

/**
 * The active alarms of `drive`, newest first, or null when this
 * drivegate has no alarms API (an older daemon).
 */
export async function activeAlarmsOf(drive) {
  try {
    const r = await get(`/api/v1/alarms?drive=${encodeURIComponent(drive)}`);
    const list = Array.isArray(r) ? r : (r && r.alarms) || [];
    return list.filter((a) => a.drive === drive && a.active !== false);
  } catch (e) {
    if (e instanceof ApiError && e.status === 404 && !(e.problem && e.problem.drive)) return null;
    throw e;
  }
}
