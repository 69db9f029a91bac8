/**
 * The gateway's web page: sign-in where the gateway has a token, then three tabs (label a scan,
 * jobs, health). A gateway of several models offers them in a selector beside the model's name:
 * the chosen one labels the scans, runs the jobs started here and gives the palette.
 * `window.rangeretPage.state` holds what the page shows, for tests and scripts.
 */

import { Api } from './api.js';
import { HealthPanel } from './health.js';
import { JobsPanel } from './jobs.js';
import { ScanPanel } from './scan-panel.js';

const state = {
  signedIn: false,
  tokenRequired: null,
  profile: null,
  model: null,
  models: null,
  modelId: null,
  health: null,
  jobs: [],
  report: null,
  scan: { rendered: false },
  tab: 'scan',
};

const api = new Api();
const scans = new ScanPanel(api, state);
const jobs = new JobsPanel(api, state);
const health = new HealthPanel(api, state);
window.rangeretPage = { state, scans, jobs, health };

const byId = (id) => document.getElementById(id);
const pageStatus = byId('page-status');

function showTab(name) {
  state.tab = name;
  for (const button of byId('tabs').querySelectorAll('button')) {
    button.setAttribute('aria-selected', String(button.dataset.tab === name));
  }
  for (const tab of document.querySelectorAll('.tab')) tab.hidden = tab.id !== `tab-${name}`;
  if (name === 'scan' && scans.view) scans.view.resize();
}

/** Show the sign-in form and nothing else; forget the token. */
function signOut(message = '') {
  state.signedIn = false;
  api.setToken(null);
  jobs.stop();
  health.stop();
  for (const tab of document.querySelectorAll('.tab')) tab.hidden = true;
  byId('tabs').hidden = true;
  byId('sign-out').hidden = true;
  byId('served').textContent = '';
  showModel(null);
  byId('model-choice').hidden = true;
  byId('sign-in').hidden = false;
  byId('sign-in-error').textContent = message;
  pageStatus.hidden = true;
}

/** Say beside the model's name when the served weights are the bundled demo weights. */
function showModel(model) {
  state.model = model;
  const note = byId('model-note');
  note.textContent = model && model.demo_weights ? model.note : '';
  note.hidden = !(model && model.demo_weights);
}

/** Use the model `id`: its profile for the scans and jobs, its note beside its name. */
async function chooseModel(id) {
  const query = `?model=${encodeURIComponent(id)}`;
  const [profile, model] = await Promise.all([
    api.json(`v1/profile${query}`),
    api.json(`v1/model${query}`),
  ]);
  state.modelId = id;
  state.profile = profile;
  showModel(model);
  scans.setProfile(profile, id);
  jobs.setModel(id, profile);
  byId('model-select').value = id;
}

/** Offer the gateway's models in the selector (shown where there are several). */
function offerModels(listing) {
  state.models = listing;
  const select = byId('model-select');
  select.replaceChildren(
    ...listing.models.map((m) => new Option(`${m.id} (${m.profile})`, m.id)),
  );
  byId('model-choice').hidden = listing.models.length < 2;
}

async function signedIn() {
  const listing = await api.json('v1/models');
  offerModels(listing);
  await chooseModel(state.modelId && listing.models.some((m) => m.id === state.modelId)
    ? state.modelId
    : listing.default);
  state.signedIn = true;
  byId('sign-in').hidden = true;
  byId('tabs').hidden = false;
  byId('sign-out').hidden = !state.tokenRequired;
  pageStatus.hidden = true;
  showTab(state.tab);
  jobs.start();
  health.start();
}

async function start() {
  try {
    const withStored = await api.health();
    if (withStored.detailed) {
      state.tokenRequired = Boolean(api.token);
      await signedIn();
      return;
    }
    state.tokenRequired = true;
    signOut(api.token ? 'The token kept in this tab is no longer accepted.' : '');
  } catch (error) {
    pageStatus.textContent = `The gateway cannot be reached: ${error.message}`;
    pageStatus.classList.add('error');
  }
}

byId('sign-in-form').addEventListener('submit', async (event) => {
  event.preventDefault();
  const field = event.target.elements.token;
  api.setToken(field.value.trim());
  try {
    const answer = await api.health();
    if (!answer.detailed) {
      signOut('The gateway does not accept this token.');
      return;
    }
    field.value = '';
    await signedIn();
  } catch (error) {
    signOut(error.message);
  }
});

byId('sign-out').addEventListener('click', () => signOut());
byId('model-select').addEventListener('change', async (event) => {
  try {
    await chooseModel(event.target.value);
  } catch (error) {
    pageStatus.textContent = error.message;
    pageStatus.hidden = false;
  }
});
byId('tabs').addEventListener('click', (event) => {
  if (event.target.dataset.tab) showTab(event.target.dataset.tab);
});
api.onUnauthorized = (detail) => signOut(detail);

start();
