"""Fitting the 19 parameters to a picture: the methods and their settings (`methods`), what one fit is asked to do
(`request`), the objective and the best-of-n search of the paper's Algorithm 1 (`search`), the optimisers
(`simplex`, `gradient`), Mitsuba in the loop after the search (`verify`, `correct`, `refine`), image sequences
(`sequence`), the stages of a fit in order (`stages`) and what they found (`outcome`), params.json (`document`),
a picture file end to end (`fitfile`), several in one process (`batch`) and the visual report (`report`).
It may import `model`, `render` and the shared base, never `app`."""
