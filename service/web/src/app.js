/**
 * The gateway's web page: sign-in where the gateway has a token, then three tabs (label a scan,
 * jobs, health). `window.rangeretPage.state` holds what the page shows, for tests and scripts.
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

async function signedIn() {
  const [profile, model] = await Promise.all([api.json('v1/profile'), api.json('v1/model')]);
  state.profile = profile;
  showModel(model);
  state.signedIn = true;
  scans.setProfile(profile);
  byId('sign-in').hidden = true;
  byId('tabs').hidden = false;
  byId('sign-out').hidden = !state.tokenRequired;
  pageStatus.hidden = true;
  showTab(state.tab);
  jobs.start(profile);
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
byId('tabs').addEventListener('click', (event) => {
  if (event.target.dataset.tab) showTab(event.target.dataset.tab);
});
api.onUnauthorized = (detail) => signOut(detail);

start();
