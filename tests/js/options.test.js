// Node's test runner on the page's form options (service/static/options.js): node --test tests/js
"use strict";
const test = require("node:test");
const assert = require("node:assert/strict");
const { htmlBounds, optionEntries, applyPageOptions } = require("../../service/static/options.js");

test("inclusive bounds are the input's min and max", () => {
  assert.deepEqual(htmlBounds({ minimum: 1, maximum: 100000 }), { min: 1, max: 100000 });
});

test("an exclusive bound becomes the first step inside it", () => {
  assert.deepEqual(htmlBounds({ exclusive_minimum: 0.05, exclusive_maximum: 1 }, 0.01), { min: 0.06, max: 0.99 });
  assert.deepEqual(htmlBounds({ exclusive_minimum: 0 }), { min: 1 });
});

test("a default is the placeholder; no bound, no attribute", () => {
  assert.deepEqual(htmlBounds({ default: 0.5 }), { placeholder: 0.5 });
  assert.deepEqual(htmlBounds({ minimum: null, default: null }), {});
});

test("the default choice is the selected one", () => {
  const select = { choices: [{ value: "tiny", label: "tiny (t)" }, { value: "fast", label: "fast (f)" }], default: "fast" };
  assert.deepEqual(optionEntries(select), [["tiny", "tiny (t)", false], ["fast", "fast (f)", true]]);
  assert.deepEqual(optionEntries({ choices: [{ value: "eva", label: "eva" }], default: null }), [["eva", "eva", false]]);
});

function fakeElement(attrs = {}, label = null) {
  return {
    attrs: { ...attrs },
    children: [],
    closest(selector) { return selector === "label" ? label : null; },
    getAttribute(name) { return name in this.attrs ? this.attrs[name] : null; },
    setAttribute(name, value) { this.attrs[name] = value; },
    append(child) { this.children.push(child); },
  };
}

test("the options fill the named form's selects and number inputs", () => {
  globalThis.Option = function Option(text, value, defaultSelected, selected) {
    Object.assign(this, { text, value, defaultSelected, selected });
  };
  const presetLabel = fakeElement();
  const preset = fakeElement({}, presetLabel);
  const scale = fakeElement({ step: "0.01", placeholder: "preset" });
  const form = {
    querySelector(selector) {
      return {
        'select[name="preset"]': preset,
        '[name="preset"]': preset,
        'input[type="number"][name="image_scale"]': scale,
        '[name="image_scale"]': scale,
      }[selector] || null;
    },
  };
  const doc = { getElementById: (id) => (id === "upload-form" ? form : null) };
  applyPageOptions(doc, {
    forms: {
      "upload-form": {
        selects: { preset: { choices: [{ value: "fast", label: "fast (f)" }], default: "fast" }, absent: { choices: [] } },
        numbers: { image_scale: { exclusive_minimum: 0, maximum: 2, default: null }, absent: { minimum: 1 } },
        hints: { preset: "Training preset.", image_scale: "Overrides the preset's.", absent: "none" },
      },
      "no-such-form": { selects: {}, numbers: {} },
    },
  });
  assert.equal(preset.children.length, 1);
  assert.deepEqual({ ...preset.children[0] }, { text: "fast (f)", value: "fast", defaultSelected: true, selected: true });
  assert.deepEqual(scale.attrs, { step: "0.01", placeholder: "preset", min: "0.01", max: "2", title: "Overrides the preset's." });
  // The tooltip goes on the label that holds the field, where the pointer rests on its text too.
  assert.deepEqual(presetLabel.attrs, { title: "Training preset." });
  assert.deepEqual(preset.attrs, {});
});
