// Submission pages: poll the JSON status until the evaluation is finished, then reload to show the scores.
document.addEventListener("DOMContentLoaded", () => {
  const el = document.getElementById("status");
  if (!el || !el.dataset.poll) return;
  const pending = (s) => s === "queued" || s === "running";
  if (!pending(el.dataset.status)) return;
  const tick = async () => {
    try {
      const r = await fetch(el.dataset.poll, { credentials: "same-origin" });
      if (r.ok) {
        const s = (await r.json()).status;
        if (!pending(s)) { window.location.reload(); return; }
        el.textContent = s;
      }
    } catch (e) { /* network hiccup: try again */ }
    setTimeout(tick, 700);
  };
  setTimeout(tick, 700);
});
