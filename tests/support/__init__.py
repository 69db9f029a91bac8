"""What the tests share besides fixtures: paths, small trees, the reference evaluation, gateway,
browser, Ray and KubeRay helpers. Imported as `tests.support.<module>`."""
