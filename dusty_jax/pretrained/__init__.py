"""Small trained generators shipped with the package, loadable offline.

    params = dusty_jax.load_pretrained('sim-dusty1')
    rec = dusty_jax.invert(params, scan, num_steps=300)

Each is one ``NAME.npz`` in this folder (numpy arrays only: loading runs no
code): the EMA generator's variables under ``variables/...``, the angle
table, and ``meta``, a JSON string of the model settings (model, sensor,
network sizes, eq-lr constants, tolerance) and where the weights came from.
They were trained by ``benchmarks/study.py`` on simulated HDL-64E scenes
(see benchmarks/results/study.md), not on real data.
"""

from __future__ import annotations

import json
import os

import jax.numpy as jnp
import numpy as np
from flax import traverse_util

HERE = os.path.dirname(os.path.abspath(__file__))


def available() -> list[str]:
  return sorted(f[:-4] for f in os.listdir(HERE) if f.endswith('.npz'))


def path_of(name: str) -> str:
  return os.path.join(HERE, f'{name}.npz')


def load_pretrained(name: str):
  """The shipped generator ``name`` as a GeneratorParams (see ``available()``)."""
  path = path_of(name)
  if not os.path.isfile(path):
    raise ValueError(f'no pretrained model {name!r}; available: {available()}')
  return load_file(path)


def load_file(path: str):
  """A generator written by :func:`export`, from any path."""
  from dusty_jax import models, sensor as sensor_lib
  with np.load(path, allow_pickle=False) as f:
    meta = json.loads(str(f['meta']))
    flat = {k[len('variables/'):]: jnp.asarray(f[k]) for k in f.files
            if k.startswith('variables/')}
    angles = jnp.asarray(f['angles'])
  spec = meta.pop('sensor')
  sensor = sensor_lib.SensorSpec(**dict(spec, elevation_deg=tuple(spec['elevation_deg'])))
  variables = traverse_util.unflatten_dict(flat, sep='/')
  meta.pop('source', None)
  return models.GeneratorParams(variables=variables, angles=angles, sensor=sensor, **meta)


def export(params, name: str, source: str = '', directory: str = HERE) -> str:
  """Writes a GeneratorParams as ``NAME.npz`` (in this package by default);
  returns the path."""
  meta = {'model': params.model, 'sensor': sensor_to_dict(params.sensor),
          'latent_dim': params.latent_dim, 'ch_base': params.ch_base,
          'ch_max': params.ch_max, 'tau': float(params.tau),
          'tolerance': float(params.tolerance), 'eqlr': params.eqlr,
          'source': source}
  flat = traverse_util.flatten_dict(params.variables, sep='/')
  arrays = {f'variables/{k}': np.asarray(v, np.float32) for k, v in flat.items()}
  path = os.path.join(directory, f'{name}.npz')
  np.savez_compressed(path, meta=np.asarray(json.dumps(meta)),
                      angles=np.asarray(params.angles, np.float32), **arrays)
  return path


def sensor_to_dict(sensor) -> dict:
  import dataclasses
  d = dataclasses.asdict(sensor)
  return {k: (np.asarray(v).tolist() if isinstance(v, (np.ndarray, tuple)) else v)
          for k, v in d.items()}
