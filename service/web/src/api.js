/**
 * The gateway's HTTP API, called relative to the page's own address (so the page works behind a
 * reverse proxy's path prefix), with the bearer token where the gateway has one. The token is
 * kept in this tab's sessionStorage only.
 */

const TOKEN_KEY = 'rangeret.token';

/** An answer of the gateway other than 2xx: its status and its one-sentence detail. */
export class ApiError extends Error {
  constructor(status, detail) {
    super(detail);
    this.status = status;
  }
}

/** The absolute URL of an API path such as `v1/scans`, relative to the page. */
export function apiUrl(path) {
  return new URL(path, document.baseURI);
}

export class Api {
  constructor() {
    this.token = sessionStorage.getItem(TOKEN_KEY);
    /** Called with the detail when a request is refused with 401. */
    this.onUnauthorized = null;
  }

  /** Keep `token` for this tab (null forgets it). */
  setToken(token) {
    this.token = token || null;
    if (this.token) sessionStorage.setItem(TOKEN_KEY, this.token);
    else sessionStorage.removeItem(TOKEN_KEY);
  }

  headers(extra = {}) {
    const headers = new Headers(extra);
    if (this.token) headers.set('Authorization', `Bearer ${this.token}`);
    return headers;
  }

  /** The response of a request; a non-2xx answer throws ApiError with the gateway's sentence. */
  async request(path, { method = 'GET', headers = {}, body, accept = 'application/json' } = {}) {
    let response;
    try {
      response = await fetch(apiUrl(path), {
        method,
        headers: this.headers({ Accept: accept, ...headers }),
        body,
      });
    } catch (error) {
      throw new ApiError(0, `The gateway cannot be reached (${error.message}).`);
    }
    if (!response.ok) {
      let detail = `The gateway answered ${response.status}.`;
      try {
        detail = (await response.json()).detail || detail;
      } catch {
        // not a JSON answer: keep the status
      }
      if (response.status === 401 && this.onUnauthorized) this.onUnauthorized(detail);
      throw new ApiError(response.status, detail);
    }
    return response;
  }

  async json(path, options) {
    return (await this.request(path, options)).json();
  }

  /**
   * `/healthz` with the token, answered 200 or 503 with a body either way. Its details (backend,
   * workers) come only with the right token, or from a gateway without one.
   */
  async health() {
    const response = await fetch(apiUrl('healthz'), {
      headers: this.headers({ Accept: 'application/json' }),
      cache: 'no-store',
    });
    const body = await response.json();
    return { status: response.status, body, detailed: 'backend' in body };
  }
}
