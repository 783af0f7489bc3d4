// Progressive enhancement of the server-rendered pages (everything also works without JavaScript).
document.addEventListener("DOMContentLoaded", () => {
  pollSubmissionStatus();
  for (const form of document.querySelectorAll("form[data-confirm]")) {
    form.addEventListener("submit", (ev) => { if (!window.confirm(form.dataset.confirm)) ev.preventDefault(); });
  }
  for (const form of document.querySelectorAll("form[data-async]")) submitInPlace(form);
  prefillCameras();
});

// Create-anchor form: choosing photos with the cameras box still empty starts one line per photo name.
function prefillCameras() {
  const input = document.getElementById("new-photos"), box = document.getElementById("cameras");
  if (!input || !box) return;
  input.addEventListener("change", () => {
    if (!box.value.trim()) box.value = [...input.files].map((f) => (/\s/.test(f.name) ? `"${f.name}"` : f.name) + " ").join("\n");
  });
}

// Submission pages: poll the JSON status until the evaluation is finished, then reload to show the scores.
function pollSubmissionStatus() {
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
}

// Forms with data-async post in the background: an error shows above the form (in its data-error-box, else
// #form-error), which stays as it is (chosen files included); a redirect is followed; a result section in the
// answer replaces the page's one.
function submitInPlace(form) {
  const boxId = form.dataset.errorBox || "form-error";
  const box = document.getElementById(boxId);
  const button = form.querySelector("button[type=submit]");
  const busy = form.querySelector(".busy");
  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    button.disabled = true;
    if (busy) busy.hidden = false;
    const show = (msg) => { box.textContent = msg; box.hidden = !msg; };
    try {
      const r = await fetch(form.action, { method: "POST", body: new FormData(form), credentials: "same-origin",
                                           headers: { Accept: "text/html" } });
      if (r.ok && r.redirected) { window.location.assign(r.url); return; }
      const doc = new DOMParser().parseFromString(await r.text(), "text/html");
      const err = [boxId, "form-error", "error-message"].map((id) => doc.getElementById(id))
        .find((e) => e && e.textContent.trim());
      show(r.ok ? "" : ((err && err.textContent.trim()) || `the server answered ${r.status}`));
      const fresh = doc.getElementById("result-section"), here = document.getElementById("result-section");
      if (r.ok && fresh && here) here.replaceWith(fresh);
      if (!r.ok) box.scrollIntoView({ block: "center" });
    } catch (e) {
      show(`could not reach the server (${e.message}); your entries are kept, try again`);
    } finally {
      button.disabled = false;
      if (busy) busy.hidden = true;
    }
  });
}
