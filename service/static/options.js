// The forms' choices and number bounds from GET /page/options (what the API checks), applied to
// the page. Pure functions first, so Node's test runner checks them (tests/js/).
"use strict";

// An input's HTML min / max from the API's bounds: HTML's are inclusive and values step from
// min, so an exclusive bound becomes the first step inside it (gt 0.05, step 0.01: min 0.06).
function htmlBounds(field, step = 1) {
  const round = (x) => Math.round(x * 1e10) / 1e10;
  const out = {};
  if (field.minimum != null) out.min = field.minimum;
  else if (field.exclusive_minimum != null) out.min = round(field.exclusive_minimum + step);
  if (field.maximum != null) out.max = field.maximum;
  else if (field.exclusive_maximum != null) out.max = round(field.exclusive_maximum - step);
  if (field.default != null) out.placeholder = field.default;
  return out;
}

// [value, label, selected] of each option to add to a select.
function optionEntries(select) {
  return select.choices.map((c) => [c.value, c.label, c.value === select.default]);
}

// Fill every form of ``options.forms`` in ``doc``: options appended to each select (after any the
// HTML has, such as "the preset's"), bounds and placeholder on each number input, and each
// field's description as the tooltip of its label (of the field itself when it has none).
function applyPageOptions(doc, options) {
  for (const [formId, form] of Object.entries(options.forms)) {
    const element = doc.getElementById(formId);
    if (!element) continue;
    for (const [name, select] of Object.entries(form.selects)) {
      const target = element.querySelector(`select[name="${name}"]`);
      if (!target) continue;
      for (const [value, label, selected] of optionEntries(select)) {
        target.append(new Option(label, value, selected, selected));
      }
    }
    for (const [name, field] of Object.entries(form.numbers)) {
      const input = element.querySelector(`input[type="number"][name="${name}"]`);
      if (!input) continue;
      const bounds = htmlBounds(field, Number(input.getAttribute("step") || 1));
      for (const [attr, value] of Object.entries(bounds)) input.setAttribute(attr, String(value));
    }
    for (const [name, hint] of Object.entries(form.hints || {})) {
      const field = element.querySelector(`[name="${name}"]`);
      if (!field) continue;
      (field.closest("label") || field).setAttribute("title", hint);
    }
  }
}

if (typeof module !== "undefined") module.exports = { htmlBounds, optionEntries, applyPageOptions };
