/**
 * "Label a scan": a dropped `.bin` goes to `POST v1/scans` (JSON answer); the scan is drawn in 3D
 * coloured by its predicted class, by its ground truth (an optional `.label`) or by error, in the
 * served profile's palette, with a legend that hides and shows classes, the points per class and,
 * with ground truth, the IoU table. With "find its objects" (a profile with thing classes) the
 * scan is labelled with `panoptic=true`: each object's points take a colour of their own, stuff
 * keeps its class's, and the objects are listed with their class and points.
 */

import { ScanView } from './scan-view.js';
import { objectColor, semanticLabels } from './objects.js';
import { classCounts, classLookup, histogram, scores, toClasses } from './scores.js';
import { count, el, fillBody, percent, saveBlob, swatch } from './dom.js';

/** Error colours (RGB), as `rangeret view` draws them: right, wrong, ignored ground truth. */
const RIGHT = [44, 160, 44];
const WRONG = [214, 39, 40];
const IGNORED = [160, 160, 160];

function rgb(hex) {
  return [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16));
}

function cssColor([r, g, b]) {
  return `rgb(${r}, ${g}, ${b})`;
}

export class ScanPanel {
  constructor(api, state) {
    this.api = api;
    this.state = state;
    this.profile = null;
    this.view = null;
    this.mode = 'prediction';
    this.hidden = new Set();
    this.scan = null; // { name, predicted, truth, instances, objects } of the scan shown
    this.status = document.getElementById('scan-status');
    this.legend = document.getElementById('legend');
    this.modes = document.getElementById('color-modes');
    this.panoptic = document.getElementById('panoptic');

    const zone = document.getElementById('drop-zone');
    const input = document.getElementById('scan-files');
    input.addEventListener('change', () => {
      if (input.files.length) this.label(input.files, performance.now());
      input.value = '';
    });
    zone.addEventListener('dragover', (event) => {
      event.preventDefault();
      zone.classList.add('dragging');
    });
    zone.addEventListener('dragleave', () => zone.classList.remove('dragging'));
    zone.addEventListener('drop', (event) => {
      event.preventDefault();
      zone.classList.remove('dragging');
      this.label(event.dataTransfer.files, performance.now());
    });
    this.modes.addEventListener('change', (event) => {
      this.mode = event.target.value;
      this.state.scan.mode = this.mode;
      this.recolor();
      this.drawLegend();
    });
    document.getElementById('show-all').addEventListener('click', () => {
      this.hidden.clear();
      this.recolor();
      this.drawLegend();
    });
    document.getElementById('save-image').addEventListener('click', async () => {
      saveBlob(await this.view.image(), `${this.scan.name.replace(/\.bin$/i, '')}-${this.mode}.png`);
    });
  }

  /** Label with the model `modelId`, whose profile gives the classes, palette and learning map. */
  setProfile(profile, modelId = null) {
    this.profile = profile;
    this.modelId = modelId;
    this.lookup = classLookup(profile);
    this.palette = profile.classes.map((cls) => rgb(cls.color));
    // Objects are offered only where the profile names thing classes.
    document.getElementById('panoptic-choice').hidden = !profile.panoptic;
    if (!profile.panoptic) this.panoptic.checked = false;
  }

  say(text, isError = false) {
    this.status.textContent = text;
    this.status.classList.toggle('error', isError);
  }

  /** Label the `.bin` among `files` (with a `.label` or `_lidarseg.bin` as ground truth) and
   * draw it. */
  async label(files, started) {
    const list = [...files];
    const isTruth = (f) => /(\.label|_lidarseg\.bin)$/i.test(f.name);
    const scanFile = list.find((f) => f.name.toLowerCase().endsWith('.bin') && !isTruth(f));
    const truthFile = list.find(isTruth);
    if (!scanFile) {
      this.say('Choose a .bin scan; a .label or _lidarseg.bin file is only its ground truth.', true);
      return;
    }
    const { point_bytes: pointBytes } = this.profile;
    const bytes = await scanFile.arrayBuffer();
    if (!bytes.byteLength || bytes.byteLength % pointBytes) {
      this.say(
        `${scanFile.name} is not a scan of the ${this.profile.profile} profile: its ` +
          `${bytes.byteLength} bytes are not a whole number of ${pointBytes}-byte points.`,
        true,
      );
      return;
    }
    const points = bytes.byteLength / pointBytes;
    let truthRaw = null;
    if (truthFile) {
      const labelBytes = this.profile.label_bytes;
      const truthBytes = await truthFile.arrayBuffer();
      if (truthBytes.byteLength !== points * labelBytes) {
        this.say(
          `${truthFile.name} holds ${truthBytes.byteLength / labelBytes} labels for the ` +
            `${points} points of ${scanFile.name}.`,
          true,
        );
        return;
      }
      truthRaw = labelBytes === 1 ? new Uint8Array(truthBytes) : new Uint32Array(truthBytes);
    }
    this.say(`Labelling ${scanFile.name} (${count(points)} points)…`);
    let answer;
    try {
      const params = new URLSearchParams();
      if (this.modelId) params.set('model', this.modelId);
      if (this.panoptic.checked && this.profile.panoptic) params.set('panoptic', 'true');
      const query = params.toString() ? `?${params}` : '';
      answer = await this.api.json(`v1/scans${query}`, {
        method: 'POST',
        headers: { 'Content-Type': 'application/octet-stream' },
        body: bytes,
      });
    } catch (error) {
      this.say(error.message, true);
      return;
    }
    if (!this.view) this.view = new ScanView(document.getElementById('viewer'));
    // A panoptic answer's labels pack each point's object beside its label.
    const withObjects = Array.isArray(answer.instances);
    const labels = withObjects ? semanticLabels(answer.labels, this.profile.panoptic) : answer.labels;
    // A profile whose predictions are class indices (nuScenes) answers them as they are.
    const predicted =
      this.profile.predictions === 'class' ? Uint8Array.from(labels) : toClasses(labels, this.lookup);
    const truth = truthRaw ? toClasses(truthRaw, this.lookup) : null;
    const instances = withObjects ? Uint32Array.from(answer.instances) : null;
    const objects = withObjects ? answer.objects : [];
    this.scan = { name: scanFile.name, predicted, truth, instances, objects };
    this.hidden.clear();
    this.mode = withObjects ? 'objects' : 'prediction';
    this.modes.querySelector(`input[value="${this.mode}"]`).checked = true;
    this.view.show(new Float32Array(bytes), pointBytes / 4);
    this.recolor();
    await this.view.drawn();
    const firstRenderMs = performance.now() - started;

    const scored = truth ? scores(predicted, truth, this.profile) : null;
    Object.assign(this.state.scan, {
      name: scanFile.name,
      points: answer.num_points,
      drawnPoints: this.view.points.geometry.getAttribute('position').count,
      classCounts: classCounts(predicted, this.profile),
      truthCounts: truth ? classCounts(truth, this.profile) : null,
      objects: withObjects ? objects.map((o) => ({ ...o })) : null,
      scores: scored,
      mode: this.mode,
      hidden: [],
      firstRenderMs,
      rendered: true,
    });
    this.modes.disabled = false;
    for (const value of ['truth', 'error']) {
      this.modes.querySelector(`input[value="${value}"]`).disabled = !truth;
    }
    this.modes.querySelector('input[value="objects"]').disabled = !withObjects;
    document.getElementById('show-all').disabled = false;
    document.getElementById('save-image').disabled = false;
    this.drawCounts();
    this.drawObjects(withObjects);
    this.drawScores(scored);
    this.drawLegend();
    const found = withObjects ? ` ${count(objects.length)} objects.` : '';
    this.say(
      `${scanFile.name}: ${count(answer.num_points)} points, labelled and drawn in ` +
        `${Math.round(firstRenderMs)} ms.${found}${truth ? ` mIoU ${percent(scored.miou)} %.` : ''}`,
    );
  }

  /** The classes that colour each point in the current mode. */
  shownClasses() {
    return this.mode === 'truth' ? this.scan.truth : this.scan.predicted;
  }

  /** Rewrite the colour of every point for the mode and the hidden classes, and draw. */
  recolor() {
    const colors = this.view.colors;
    const shown = this.shownClasses();
    const { predicted, truth } = this.scan;
    const hidden = new Uint8Array(this.profile.classes.length);
    for (const index of this.hidden) hidden[index] = 1;
    const ignored = this.profile.classes.map((cls) => cls.ignored);
    const instances = this.mode === 'objects' ? this.scan.instances : null;
    const objectColors = new Map();
    for (let i = 0, o = 0; i < shown.length; i++, o += 4) {
      const c = shown[i];
      let color;
      if (this.mode === 'error') {
        if (ignored[truth[i]]) color = IGNORED;
        else color = predicted[i] === truth[i] ? RIGHT : WRONG;
      } else if (instances && instances[i]) {
        const id = instances[i];
        if (!objectColors.has(id)) objectColors.set(id, objectColor(id));
        color = objectColors.get(id);
      } else {
        color = this.palette[c];
      }
      colors[o] = color[0];
      colors[o + 1] = color[1];
      colors[o + 2] = color[2];
      colors[o + 3] = hidden[c] ? 0 : 255;
    }
    this.view.colorsChanged();
    this.state.scan.hidden = [...this.hidden].map((index) => this.profile.classes[index].name);
  }

  /** The legend: the classes present (by the mode's classes), each with a show/hide box. */
  drawLegend() {
    const counts = histogram(this.shownClasses(), this.profile.classes.length);
    const items = [];
    if (this.mode === 'error') {
      items.push(
        el(
          'p',
          { class: 'error-key' },
          swatch(cssColor(RIGHT)),
          ' right ',
          swatch(cssColor(WRONG)),
          ' wrong ',
          swatch(cssColor(IGNORED)),
          ' ignored ground truth',
        ),
        el('p', { class: 'hint', text: 'Hide points by their predicted class:' }),
      );
    } else if (this.mode === 'objects') {
      items.push(
        el('p', {
          class: 'hint',
          text: "Each object's points take its own colour; the other points their class's.",
        }),
      );
    }
    this.profile.classes.forEach((cls, index) => {
      if (!counts[index]) return;
      const box = el('input', {
        type: 'checkbox',
        checked: !this.hidden.has(index),
        'data-class': cls.name,
        onchange: (event) => {
          if (event.target.checked) this.hidden.delete(index);
          else this.hidden.add(index);
          this.recolor();
        },
      });
      items.push(
        el(
          'label',
          { class: 'legend-item' },
          box,
          swatch(cls.color),
          el('span', { class: 'name', text: cls.name }),
          el('span', { class: 'count', text: count(counts[index]) }),
        ),
      );
    });
    this.legend.replaceChildren(...items);
  }

  drawCounts() {
    const { classCounts: predicted, truthCounts: truth } = this.state.scan;
    const rows = this.profile.classes
      .filter((cls) => predicted[cls.name] || (truth && truth[cls.name]))
      .map((cls) =>
        el(
          'tr',
          { 'data-class': cls.name },
          el('td', {}, swatch(cls.color), ` ${cls.name}`),
          el('td', { text: count(predicted[cls.name] || 0) }),
          el('td', { text: truth ? count(truth[cls.name] || 0) : '–' }),
        ),
      );
    fillBody(document.getElementById('class-counts'), rows);
  }

  /** The objects of a panoptic answer: each with its colour, id, class and points. */
  drawObjects(withObjects) {
    const box = document.getElementById('objects');
    box.hidden = !withObjects;
    if (!withObjects) return;
    const { objects } = this.scan;
    document.getElementById('objects-title').textContent = `Objects (${count(objects.length)})`;
    fillBody(
      document.getElementById('object-list'),
      objects.map((object) =>
        el(
          'tr',
          { 'data-object': object.instance, 'data-class': object.class_name },
          el('td', {}, swatch(cssColor(objectColor(object.instance))), ` ${object.instance}`),
          el('td', { text: object.class_name }),
          el('td', { text: count(object.points) }),
        ),
      ),
    );
  }

  drawScores(scored) {
    const box = document.getElementById('scores');
    box.hidden = !scored;
    if (!scored) return;
    const table = document.getElementById('iou-table');
    fillBody(
      table,
      this.profile.classes
        .filter((cls) => !cls.ignored)
        .map((cls) =>
          el(
            'tr',
            { 'data-class': cls.name },
            el('td', {}, swatch(cls.color), ` ${cls.name}`),
            el('td', { text: percent(scored.iou[cls.name]) }),
          ),
        ),
    );
    table.tFoot.replaceChildren(
      el('tr', {}, el('th', { text: 'mIoU' }), el('td', { text: percent(scored.miou) })),
      el('tr', {}, el('th', { text: 'accuracy' }), el('td', { text: percent(scored.accuracy) })),
      el('tr', {}, el('th', { text: 'points scored' }), el('td', { text: count(scored.points) })),
    );
  }
}
