"""The `pbrfit` command: parsing, exit codes and the dispatch to a command (`main`); every
command's flags, their limits and the exit statuses (`parser`); a module per command, each with
a ``run(args)``: `fit`, `render`, `synth`, `demo`, `check_grads`; the `--model` flag of fit and
render (`model_flag`) and a command's cache folder (`cache`).

May import every room; nothing imports it. The parser imports no JAX: it takes the options'
defaults and choices from the rooms' modules free of it (`pbrfit.fitting.defaults`,
`pbrfit.lighting.settings`, `pbrfit.physics.model`), so ``pbrfit --help`` and a usage error load
none of the fit's stack; `main` imports a command's module once its arguments are parsed.
"""
