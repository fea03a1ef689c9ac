// The batch report's only behaviour: the tag, category and image filters, and a scene's facts on a
// click. Data comes from the JSON block in the page; text is set with textContent, never as HTML.
(function () {
  "use strict";
  const scenes = JSON.parse(document.getElementById("scene-data").textContent);
  const byId = new Map(scenes.map((s) => [s.id, s]));
  const cards = Array.from(document.querySelectorAll("figure.scene"));
  const tagFilter = document.getElementById("tag-filter");
  const categoryFilter = document.getElementById("category-filter");
  const viewFilter = document.getElementById("view-filter");
  const shown = document.getElementById("shown-count");

  function applyFilters() {
    const tag = tagFilter.value;
    const category = categoryFilter.value;
    let n = 0;
    for (const card of cards) {
      const tags = card.dataset.tags ? card.dataset.tags.split(" ") : [];
      const visible = (!tag || tags.includes(tag)) && (!category || card.dataset.category === category);
      card.hidden = !visible;
      n += visible ? 1 : 0;
    }
    shown.textContent = String(n);
  }

  function applyView() {
    const view = viewFilter.value;
    for (const img of document.querySelectorAll("figure.scene img")) {
      const src = img.dataset[view];
      if (src) img.src = src;
    }
  }

  function cell(row, text, cls) {
    const td = document.createElement("td");
    td.textContent = text === null || text === undefined ? "" : String(text);
    if (cls) td.className = cls;
    row.appendChild(td);
  }

  function table(parent, headers, rows) {
    const t = document.createElement("table");
    const head = t.insertRow();
    for (const h of headers) {
      const th = document.createElement("th");
      th.textContent = h;
      head.appendChild(th);
    }
    for (const r of rows) {
      const tr = t.insertRow();
      r.forEach((v, i) => cell(tr, v, i === 0 ? "" : typeof v === "number" ? "num" : ""));
    }
    parent.appendChild(t);
  }

  function heading(parent, text) {
    const h = document.createElement("h3");
    h.textContent = text;
    parent.appendChild(h);
  }

  function fmt(v) {
    return Array.isArray(v) ? v.map((x) => (typeof x === "number" ? x.toFixed(4) : x)).join(", ") : v;
  }

  function showFacts(id) {
    const s = byId.get(id);
    const dialog = document.getElementById("facts");
    document.getElementById("facts-title").textContent = s.id + ": " + s.category + " (" + s.target + ")";
    const body = document.getElementById("facts-body");
    body.replaceChildren();
    const images = document.createElement("div");
    images.className = "images";
    for (const [camera, kinds] of Object.entries(s.thumbs || {})) {
      for (const kind of ["rgb", "depth", "seg"]) {
        if (!kinds[kind]) continue;
        const img = document.createElement("img");
        img.src = kinds[kind];
        img.alt = camera + " " + kind;
        img.title = camera + " " + kind;
        images.appendChild(img);
      }
    }
    body.appendChild(images);
    heading(body, "Scene");
    table(body, ["field", "value"], [
      ["proposal index", s.proposal_index], ["seed", s.seed], ["target", s.target],
      ["target category", s.category], ["folder", s.folder],
    ]);
    heading(body, "Tags (measured on the settled scene)");
    table(body, ["tag", "holds", "value", "threshold", "unit"], Object.entries(s.tags).map(
      ([t, v]) => [t, v.holds ? "yes" : "no", v.value, v.threshold, v.unit]));
    heading(body, "Settled objects");
    table(body, ["name", "asset", "category", "on", "position (m)", "quaternion (wxyz)"], s.objects.map(
      (o) => [o.name, o.asset, o.category, o.support, fmt(o.position), fmt(o.quat)]));
    if (s.furniture.length) {
      heading(body, "Furniture");
      table(body, ["name", "kind", "position", "yaw"], s.furniture.map(
        (f) => [f.name, f.kind, fmt(f.position), f.yaw]));
    }
    heading(body, "Provenance");
    table(body, ["field", "value"], Object.entries(s.provenance).map(
      ([k, v]) => [k, typeof v === "object" ? JSON.stringify(v) : v]));
    heading(body, "Checksums (sha256)");
    const sums = document.createElement("div");
    sums.className = "mono";
    table(sums, ["file", "sha256"], Object.entries(s.checksums));
    body.appendChild(sums);
    dialog.showModal();
  }

  tagFilter.addEventListener("change", applyFilters);
  categoryFilter.addEventListener("change", applyFilters);
  viewFilter.addEventListener("change", applyView);
  for (const card of cards) card.addEventListener("click", () => showFacts(card.dataset.id));
  document.getElementById("facts-close").addEventListener("click", () => document.getElementById("facts").close());
  applyFilters();
})();
