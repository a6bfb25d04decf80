// The turn clock as nurses read it, shared by the live view and the ward.
"use strict";

function clock(seconds) {
  if (seconds === null || seconds === undefined) return "-";
  const sign = seconds < 0 ? "overdue " : "";
  const s = Math.abs(Math.round(seconds));
  return `${sign}${Math.floor(s / 3600)} h ${String(Math.floor(s % 3600 / 60)).padStart(2, "0")} min`;
}
