"""Rendering the material test scene: the scene as plain data (`scene`), the Mitsuba renderer (`engine`), renderers
that work beside the caller on a thread or in a child process and the child's protocol (`process`), the named
materials (`presets`), the Mitsuba XML and Blender exports (`export`, `blender_material`) and Cycles against Mitsuba
(`blender`; `blender_scene` runs inside Blender's own Python). It may import the shared base (`matfit.params`,
`matfit.errors`, `matfit.images`, `matfit.files`, ...) and nothing from `model`, `fit` or `app`."""
