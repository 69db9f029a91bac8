/** The API page (`/docs`): Swagger UI, served by the gateway itself, over its `openapi.json`.
 * The URL is relative, so the page works behind a reverse proxy's path prefix. */
window.SwaggerUIBundle({
  url: 'openapi.json',
  dom_id: '#swagger-ui',
  deepLinking: true,
  validatorUrl: null, // no badge fetched from a validator on another host
});
