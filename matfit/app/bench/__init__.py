"""Every benchmark, one module each: the reachable targets and the judge they share (`reachable`), the fitting
methods compared (`fits`, `matfit bench-fit`), the sequence table (`sequence`, `matfit bench-sequence`), the edit
suite's main table (`suite`), optimisers (`optimisers`) and report (`suite_report`, `matfit bench`), the renderer's
and the model's speed (`speed`, `matfit bench-render` and `bench-model`), the page's latency (`page`,
`matfit bench-serve`), what the picture decides, calibrated (`ranges`, `matfit bench-ranges`). They may import
every part below `app` and `matfit.app.serve`."""
