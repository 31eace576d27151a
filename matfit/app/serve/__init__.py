"""The edit-and-see loop: a local web page that fits what the artist saves, with the CLI's own fitting and exports.

`studio` holds the model, its renderers, the one worker and every job; `jobs` a job and the page's view of its
result; `uploads` what the page may send (the caps, the checks); `watch` the watched file or folder; `routes` the
JSON API; `server` the checks before start, the server in a thread and `matfit serve`. The page itself is
`matfit/static/`. They may import every part below `app`."""
