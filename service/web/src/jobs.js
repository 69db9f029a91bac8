/**
 * "Jobs": every job with its state and live progress (`GET v1/jobs`, polled), a job's report,
 * downloads of its predictions archive and report, cancelling and removing jobs, and starting
 * jobs from an uploaded archive or from a dataset on the server, panoptic ones (objects too)
 * where the model's profile names thing classes.
 */

import { count, el, fillBody, percent, saveBlob } from './dom.js';
import { panopticReportView, panopticScores, reportView } from './report.js';

const ACTIVE = new Set(['queued', 'running']);
const POLL_ACTIVE_MS = 1000;
const POLL_IDLE_MS = 4000;
/**
 * Every report plot is shown at this share of its pixels (they are all saved at 120 dpi), so that
 * all are drawn at one scale: a narrow plot is not shown larger than a wide one shrunk to fit.
 */
const PLOT_SCALE = 0.42;

export class JobsPanel {
  constructor(api, state) {
    this.api = api;
    this.state = state;
    this.profile = null;
    this.timer = null;
    this.running = false;
    /** The id of the job whose state the status line follows (the one started last). */
    this.followed = null;
    this.table = document.getElementById('jobs-table');
    this.status = document.getElementById('jobs-status');
    this.report = document.getElementById('report');
    document.getElementById('archive-form').addEventListener('submit', (event) => {
      event.preventDefault();
      this.upload(event.target);
    });
    document.getElementById('dataset-form').addEventListener('submit', (event) => {
      event.preventDefault();
      this.startDataset(event.target);
    });
  }

  say(text, isError = false) {
    this.status.textContent = text;
    this.status.classList.toggle('error', isError);
  }

  /** Keep the status line on the job started last until it ends, in its final state. */
  follow(job) {
    const name = `Job ${job.id.slice(0, 8)}`;
    const scans = `${count(job.done)} / ${count(job.total)} scans`;
    const failed = job.failed ? `, ${count(job.failed)} failed` : '';
    const miou = job.metrics ? `, mIoU ${percent(job.metrics.miou)} %` : '';
    const pq = job.metrics && job.metrics.pq != null ? `, PQ ${percent(job.metrics.pq)} %` : '';
    const reason = job.reason ? `: ${job.reason.replace(/\.$/, '')}` : '';
    const text = {
      queued: `${name} is queued.`,
      running: `${name} is running: ${scans}${failed}.`,
      succeeded: `${name} succeeded: ${scans}${failed}${miou}${pq}.`,
      failed: `${name} failed${reason}.`,
      cancelled: `${name} was cancelled${reason}.`,
    }[job.state];
    this.say(text || `${name} is ${job.state}.`, job.state === 'failed');
    if (!ACTIVE.has(job.state)) this.followed = null;
  }

  /** Start the jobs of the model `modelId` (its `profile` reads their reports). */
  setModel(modelId, profile) {
    this.modelId = modelId;
    this.profile = profile;
    for (const choice of document.querySelectorAll('.panoptic-job')) {
      choice.hidden = !profile.panoptic;
      if (!profile.panoptic) choice.querySelector('input').checked = false;
    }
  }

  start() {
    this.running = true;
    this.poll();
  }

  /** The profile of the job's model: the chosen model's, or asked for once per other model. */
  async profileOf(modelId) {
    if (!modelId || modelId === this.modelId) return this.profile;
    this.profiles = this.profiles || new Map();
    if (!this.profiles.has(modelId)) {
      this.profiles.set(
        modelId,
        await this.api.json(`v1/profile?model=${encodeURIComponent(modelId)}`),
      );
    }
    return this.profiles.get(modelId);
  }

  stop() {
    this.running = false;
    clearTimeout(this.timer);
  }

  async poll() {
    clearTimeout(this.timer);
    if (!this.running) return;
    let active = false;
    try {
      const { jobs } = await this.api.json('v1/jobs');
      this.state.jobs = jobs;
      active = jobs.some((job) => ACTIVE.has(job.state));
      this.draw(jobs);
    } catch (error) {
      this.say(error.message, true);
    }
    if (this.running) this.timer = setTimeout(() => this.poll(), active ? POLL_ACTIVE_MS : POLL_IDLE_MS);
  }

  draw(jobs) {
    const followed = this.followed && jobs.find((job) => job.id === this.followed);
    if (followed) this.follow(followed);
    fillBody(
      this.table,
      jobs.map((job) => {
        const progress = el('progress', { max: job.total || 1, value: job.done });
        const actions = [];
        if (job.state === 'succeeded') {
          if (job.metrics) {
            actions.push(
              el('button', { type: 'button', text: 'Report', onclick: () => this.showReport(job) }),
            );
          }
          actions.push(this.download(job, 'predictions', `${job.id}-predictions.zip`, 'Predictions'));
          if (job.metrics) actions.push(this.download(job, 'report', `${job.id}-report.json`, 'Report JSON'));
        }
        actions.push(
          el('button', {
            type: 'button',
            text: ACTIVE.has(job.state) ? 'Cancel' : 'Remove',
            onclick: () => this.remove(job),
          }),
        );
        return el(
          'tr',
          { 'data-job': job.id, 'data-state': job.state },
          el('td', { class: 'mono', title: job.id, text: job.id.slice(0, 8) }),
          el('td', { text: job.panoptic ? `${job.kind}, panoptic` : job.kind }),
          el('td', { text: job.sequences.join(' ') }),
          el('td', { class: `state ${job.state}`, text: job.state, title: job.reason || '' }),
          el(
            'td',
            {},
            progress,
            ` ${count(job.done)} / ${count(job.total)}${job.failed ? `, ${job.failed} failed` : ''}`,
          ),
          el('td', { text: job.metrics ? percent(job.metrics.miou) : '–' }),
          el('td', { text: new Date(job.created).toLocaleString() }),
          el('td', { class: 'actions' }, actions),
        );
      }),
    );
  }

  /** A link to one of a job's files, fetched with the token and saved under `name`. */
  download(job, what, name, text) {
    const path = `v1/jobs/${job.id}/${what}`;
    return el('a', {
      href: path,
      class: 'button',
      'data-download': what,
      text,
      onclick: async (event) => {
        event.preventDefault();
        try {
          const response = await this.api.request(path, { accept: '*/*' });
          saveBlob(await response.blob(), name);
        } catch (error) {
          this.say(error.message, true);
        }
      },
    });
  }

  async showReport(job) {
    try {
      const report = await this.api.json(`v1/jobs/${job.id}/report`);
      const profile = await this.profileOf(job.model);
      const panoptic = report.task === 'panoptic';
      const view = panoptic ? panopticReportView : reportView;
      this.report.replaceChildren(...view(report, job, profile));
      this.report.hidden = false;
      this.state.report = {
        job: job.id,
        miou: report.miou,
        sequences: Object.keys(report.per_sequence || {}),
        bands: (report.per_distance || []).length,
        plots: [],
      };
      if (panoptic) {
        const overall = panopticScores(report);
        Object.assign(this.state.report, {
          panoptic: true,
          miou: overall.miou,
          pq: overall.pq,
          classes: Object.keys(overall.classes),
        });
      }
      this.report.scrollIntoView({ block: 'start' });
      await this.showPlots(job);
    } catch (error) {
      this.say(error.message, true);
    }
  }

  /** The report's PNGs, fetched with the token (an <img> cannot send it) and shown as blobs. */
  async showPlots(job) {
    for (const url of this.plotUrls || []) URL.revokeObjectURL(url);
    this.plotUrls = [];
    const box = el('div', { class: 'report-plots', id: 'report-plots' });
    this.report.append(box);
    for (const name of job.plots || []) {
      const response = await this.api.request(`v1/jobs/${job.id}/plots/${name}`, {
        accept: 'image/png',
      });
      const url = URL.createObjectURL(await response.blob());
      this.plotUrls.push(url);
      const image = el('img', { src: url, alt: name, 'data-plot': name });
      image.addEventListener(
        'load',
        () => {
          image.width = Math.round(image.naturalWidth * PLOT_SCALE);
        },
        { once: true },
      );
      box.append(el('figure', {}, image, el('figcaption', { text: name })));
      this.state.report.plots.push(name);
    }
  }

  async remove(job) {
    if (this.followed === job.id) this.followed = null;
    try {
      await this.api.json(`v1/jobs/${job.id}`, { method: 'DELETE' });
      if (this.state.report && this.state.report.job === job.id) {
        this.report.hidden = true;
        this.state.report = null;
      }
      this.say(`Job ${job.id.slice(0, 8)} ${ACTIVE.has(job.state) ? 'cancelled' : 'removed'}.`);
    } catch (error) {
      this.say(error.message, true);
    }
    this.poll();
  }

  async upload(form) {
    const file = form.elements.archive.files[0];
    if (!file) {
      this.say('Choose an archive to upload.', true);
      return;
    }
    const body = new FormData();
    body.append('archive', file, file.name);
    this.say(`Uploading ${file.name}…`);
    const panoptic = form.elements.panoptic.checked ? '&panoptic=true' : '';
    const path = `v1/jobs/uploads?model=${encodeURIComponent(this.modelId)}${panoptic}`;
    await this.create(body, {}, path);
    form.reset();
  }

  async startDataset(form) {
    const dataset = form.elements.dataset.value.trim();
    const split = form.elements.split.value;
    const sequences = form.elements.sequences.value.split(/[\s,]+/).filter(Boolean);
    if (!split && !sequences.length) {
      this.say('Name the sequences, or choose a split.', true);
      return;
    }
    const request = split ? { dataset, split } : { dataset, sequences };
    request.model = this.modelId;
    if (form.elements.panoptic.checked) request.panoptic = true;
    await this.create(JSON.stringify(request), { 'Content-Type': 'application/json' });
  }

  /** Start a job: a dataset's JSON at `v1/jobs`, an archive's form at `v1/jobs/uploads`. */
  async create(body, headers = {}, path = 'v1/jobs') {
    try {
      const created = await this.api.json(path, { method: 'POST', headers, body });
      this.followed = created.id;
      this.say(`Job ${created.id.slice(0, 8)} is queued.`);
    } catch (error) {
      this.say(error.message, true);
    }
    this.poll();
  }
}
