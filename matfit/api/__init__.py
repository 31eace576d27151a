"""The public API's machinery, whose names the package `matfit` lists (docs/api.md): the material and its forms
(`material`: `Material`, `render`), what a fit gives back (`results`: `Outputs`, `Fit`), fitting pictures (`fitter`:
`Fitter`, `fit`, `load_model`) and sequences (`sequences`: `fit_sequence`), and the checks of their arguments
(`arguments`). JAX, Mitsuba and OpenImageIO are imported by the functions that need them, so that `import matfit`
loads NumPy and the parameter table alone. It may import `fitting`, `model`, `rendering` and the shared base, never
`app` (the command line, the page and the benchmarks are layers over it)."""
