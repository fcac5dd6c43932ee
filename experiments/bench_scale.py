"""``make bench`` sections on scale: seconds per iteration versus seeds, on one device and with the seed axis split
over host devices (section ``seeds``), per-core efficiency of the GRU steps against a plain matmul measured in
the same process (section ``efficiency``), where an iteration of the default job goes (section ``profile``), and
the GRU's gradient steps against the minGRU's (``model.cell``; ``python experiments/bench_scale.py --cells``, on one
core), and the GRU's sequence in three layouts of the same arithmetic (section ``layouts``). Each device count runs
in its own process (a process's CPU device count is fixed when JAX starts), unpinned, so a 2-device process may use
both cores.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time

SEEDS = (1, 2, 4, 8)
ITERS = 3


def seeds_and_devices() -> None:
    """Print s/iteration of dil at the bandit CPU preset for 1, 2, 4, 8 seeds on 1 device and on 2 host devices."""
    print(f"\n## bandit CPU preset, dil: seconds per iteration ({ITERS}-iteration chunk, after its compile) versus")
    print("##  seeds; one device, and the seed axis split over 2 host devices (--host-devices 2); a process, unpinned")
    for devices in (1, 2):
        proc = subprocess.run([sys.executable, __file__, "--devices", str(devices)], capture_output=True, text=True,
                              timeout=1800, check=False)
        rows = [line for line in proc.stdout.splitlines() if line.startswith("devices=")]
        print("\n".join(rows) if rows else f"devices={devices}: failed (exit {proc.returncode}) "
              f"{proc.stderr.strip().splitlines()[-1:]}", flush=True)


def devices_one(devices: int) -> None:
    """One process of ``seeds_and_devices``: its rows, and at 8 seeds on one device vmap against one seed at a time."""
    import jax

    jax.config.update("jax_num_cpu_devices", devices)
    from jaxdeconf.resolve import build
    from jaxdeconf.sharding import seed_layout
    from jaxdeconf.train import build_algorithm, compiled_chunk, initial_states

    batches = (1, 0) if devices == 1 else (1,)
    for seeds in SEEDS:
        for batch in batches if seeds == SEEDS[-1] else (1,):
            config = build("bandit", "cpu", ("dil",), seeds, {"train.warmup": "0", "train.seed_batch": str(batch)})
            algo, layout = build_algorithm(config, "dil"), seed_layout(seeds)
            states = initial_states(algo, config, layout)
            t0 = time.perf_counter()
            program = compiled_chunk(algo, ITERS, layout).lower(states).compile()
            compile_s = time.perf_counter() - t0
            jax.block_until_ready(program(states))  # Warm.
            t0 = time.perf_counter()
            jax.block_until_ready(program(states))
            s = (time.perf_counter() - t0) / ITERS
            how = "one seed at a time" if batch == 1 else "all seeds vmapped"
            print(f"devices={devices} seeds={seeds}: {s:6.3f} s/iteration, {s / seeds:6.3f} s per seed ({how}; "
                  f"{layout.padded} trained; compile {compile_s:.1f} s)", flush=True)


def efficiency() -> None:
    """Achieved GFLOP/s of the GRU's steps (a scan over 100 steps, batch 32, the CPU preset's sizes, forward and
    backward) against a plain 1024^3 matmul's, in this process on one core."""
    import flax.linen as nn
    import jax
    import jax.numpy as jnp

    print("\n## Per-core efficiency: GRU steps (hidden 64, input 64, batch 32, 100 steps) against a plain matmul")
    steps, batch, size = 100, 32, 64
    cell = nn.GRUCell(size)
    x = jax.random.normal(jax.random.key(0), (steps, batch, size))
    params = cell.init(jax.random.key(1), jnp.zeros((batch, size)), x[0])

    def forward(p: object, x: jax.Array) -> jax.Array:
        return jax.lax.scan(lambda c, xt: cell.apply(p, c, xt), jnp.zeros((batch, size)), x)[1]

    step_flops = 2 * batch * 6 * size * size  # Six [batch, 64] x [64, 64] products per step (3 gates, x and h).
    backward = jax.jit(jax.grad(lambda p, x: jnp.sum(forward(p, x) ** 2)))
    rows = {"GRU forward": (jax.jit(forward), step_flops * steps),
            "GRU forward + backward": (backward, 3 * step_flops * steps)}
    for label, (fn, flops) in rows.items():
        print(f"{label:24s}: {flops / _best(fn, params, x) / 1e9:6.1f} GFLOP/s (matmul FLOPs only)")
    a = jax.random.normal(jax.random.key(2), (1024, 1024))
    print(f"{'matmul 1024^3':24s}: {2 * 1024**3 / _best(jax.jit(jnp.matmul), a, a) / 1e9:6.1f} GFLOP/s")


def profile(seeds: int = 10) -> None:
    """Milliseconds of each part of an iteration of the default job (bandit CPU preset, ``seeds`` seeds vmapped, one
    core): data collection, the inference model's ELBO steps, the policy's BC steps (dil's include encoding the expert
    buffer once), and one evaluation."""
    import jax

    from jaxdeconf.resolve import build
    from jaxdeconf.train import build_algorithm

    print(f"\n## Default job, bandit CPU preset, {seeds} seeds vmapped: milliseconds per part of an iteration")
    for name in ("bc", "dil"):
        config = build("bandit", "cpu", (name,), seeds, {"train.warmup": "0"})
        algo = build_algorithm(config, name)
        k_init, k_parts = jax.random.split(jax.random.key(0))
        states = jax.jit(jax.vmap(algo.init))(jax.random.split(k_init, seeds))
        keys = jax.random.split(k_parts, seeds)
        ms = {}
        for label, fn in (("collect expert", algo.collect_expert), ("collect own", algo.collect_explore),
                          ("encoder steps", algo.update_encoder)):  # Each fills the buffers the next parts read.
            fn = jax.jit(jax.vmap(fn))
            states = fn(states, keys)[0]
            ms[label] = 1e3 * _best(fn, states, keys, reps=3)
        ms["policy steps"] = 1e3 * _best(jax.jit(jax.vmap(algo.update_policy)), states, keys, reps=3)
        ms["evaluation"] = 1e3 * _best(jax.jit(jax.vmap(algo.evaluate)), states, keys, reps=3)
        t = config.train
        print(f"{name:4s}: " + ", ".join(f"{k} {v:.0f}" for k, v in ms.items())
              + f" ms ({t.encoder_steps if name == 'dil' else 0} ELBO and {t.policy_steps} BC steps per iteration; "
              f"one evaluation per {t.chunk} iterations)", flush=True)


def cells(seed_counts: tuple[int, ...] = (1, 10)) -> None:
    """Milliseconds per BC gradient step (bc's ``update_policy``) and per ELBO step (dil's ``update_encoder``) at the
    bandit CPU preset (width 32, hidden 32, batch 32, 100 steps), GRU against minGRU, the seeds vmapped."""
    print("\n## bandit CPU preset: ms per gradient step, model.cell=gru against mingru, seeds vmapped")
    for seeds in seed_counts:
        ms = {cell: _cell_steps(cell, seeds) for cell in ("gru", "mingru")}
        for part in ("BC step", "ELBO step"):
            gru, mingru = ms["gru"][part], ms["mingru"][part]
            print(f"seeds={seeds:2d} {part:9s}: gru {gru:7.2f} ms, mingru {mingru:7.2f} ms, "
                  f"gru / mingru {gru / mingru:5.2f}", flush=True)


def _cell_steps(cell: str, seeds: int) -> dict[str, float]:
    """``cells``' milliseconds per BC and per ELBO step of one cell at ``seeds`` seeds vmapped."""
    import jax

    from jaxdeconf.resolve import build
    from jaxdeconf.train import build_algorithm

    ms = {}
    for name, part in (("bc", "BC step"), ("dil", "ELBO step")):
        config = build("bandit", "cpu", (name,), seeds, {"train.warmup": "0", "model.cell": cell})
        algo = build_algorithm(config, name)
        k_init, k_parts = jax.random.split(jax.random.key(0))
        states = jax.jit(jax.vmap(algo.init))(jax.random.split(k_init, seeds))
        keys = jax.random.split(k_parts, seeds)
        for fn in (algo.collect_expert, algo.collect_explore):  # Fill the buffers the steps sample.
            states = jax.jit(jax.vmap(fn))(states, keys)[0]
        update, steps = ((algo.update_policy, config.train.policy_steps) if name == "bc"
                         else (algo.update_encoder, config.train.encoder_steps))
        ms[part] = 1e3 * _best(jax.jit(jax.vmap(update)), states, keys, reps=5) / steps
    return ms


def layouts(shapes: tuple[tuple[int, int, int, int], ...] = ((32, 32, 100, 1), (32, 32, 100, 10), (64, 8, 200, 1),
                                                             (64, 8, 200, 5))) -> None:
    """Milliseconds per gradient of a recurrent policy's teacher-forced sequence (GRU, width = hidden) in three
    layouts of the same arithmetic: the shipped one (``losses.recurrent_policy_scan``: cell and readout every step),
    the readout hoisted out of the loop, and the readout hoisted with every step's three input projections computed
    for the whole sequence at once and the three recurrent ones as one matmul. Timed in turn, round by round, so load
    from other processes falls on all three alike; (hidden, batch, steps, seeds vmapped) per row."""
    import jax
    import jax.numpy as jnp

    from jaxdeconf import losses
    from jaxdeconf.models import RecurrentPolicy

    print("\n## GRU sequence layouts: ms per gradient of a recurrent policy's sequence loss, best of 15 rounds")
    layout_fns = {"shipped": losses.recurrent_policy_scan, "readout hoisted": _readout_hoisted,
                  "fused": _fused_projections}
    for hidden, batch, steps, seeds in shapes:
        policy = RecurrentPolicy(hidden, 16, hidden, 5)
        k_obs, k_act, k_init = jax.random.split(jax.random.key(0), 3)
        obs = jax.random.normal(k_obs, (seeds, steps, batch, 6))
        prev = jax.random.normal(k_act, (seeds, steps, batch, 5))
        params = jax.vmap(lambda k, p=policy: p.init(k, jnp.zeros((1, 6)), jnp.zeros((1, 5))))(
            jax.random.split(k_init, seeds))
        outs = {name: jax.jit(jax.vmap(lambda p, o, a, f=fn, n=policy: f(n, p, o, a)))(params, obs, prev)
                for name, fn in layout_fns.items()}
        diff = max(float(jnp.max(jnp.abs(out - outs["shipped"]))) for out in outs.values())
        grads = {name: jax.jit(jax.vmap(jax.grad(lambda p, o, a, f=fn, n=policy: jnp.sum(f(n, p, o, a) ** 2))))
                 for name, fn in layout_fns.items()}
        times = {name: [] for name in grads}
        for _ in range(16):  # The first round compiles and warms up.
            for name, grad in grads.items():
                t0 = time.perf_counter()
                jax.block_until_ready(grad(params, obs, prev))
                times[name].append(time.perf_counter() - t0)
        best = {name: min(t[1:]) for name, t in times.items()}
        print(f"hidden {hidden}, batch {batch}, {steps} steps, {seeds:2d} seeds: " + ", ".join(
            f"{name} {1e3 * t:.2f} ms ({best['shipped'] / t:.2f}x)" for name, t in best.items())
              + f"; outputs within {diff:.1e} of the shipped layout's", flush=True)


def _readout_hoisted(policy: object, params: object, obs: object, prev: object) -> object:
    """``layouts``: the GRU cell alone in the loop, the head on every state at once."""
    import jax
    import jax.numpy as jnp

    from jaxdeconf.models import RecurrentPolicy

    inputs = policy.apply(params, obs, prev, method=RecurrentPolicy.embed)
    carry = jnp.zeros((*obs.shape[1:-1], policy.hidden), jnp.float32)
    states = jax.lax.scan(lambda c, x: policy.apply(params, c, x, method=lambda m, c, x: m.cell(c, x)), carry,
                          inputs)[1]
    return policy.apply(params, states, method=RecurrentPolicy.readout)


def _fused_projections(policy: object, params: object, obs: object, prev: object) -> object:
    """``layouts``: flax's GRUCell arithmetic with its input projections over the whole sequence and its recurrent
    ones as one matmul per step, the head on every state at once."""
    import jax
    import jax.numpy as jnp

    from jaxdeconf.models import RecurrentPolicy

    cell = params["params"]["cell"]
    w_in = jnp.concatenate([cell[g]["kernel"] for g in ("ir", "iz", "in")], axis=-1)
    b_in = jnp.concatenate([cell[g]["bias"] for g in ("ir", "iz", "in")])
    w_h = jnp.concatenate([cell[g]["kernel"] for g in ("hr", "hz", "hn")], axis=-1)
    projected = policy.apply(params, obs, prev, method=RecurrentPolicy.embed) @ w_in + b_in

    def step(h: jax.Array, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        xr, xz, xn = jnp.split(x, 3, axis=-1)
        hr, hz, hn = jnp.split(h @ w_h, 3, axis=-1)
        r, z = jax.nn.sigmoid(xr + hr), jax.nn.sigmoid(xz + hz)
        h = (1.0 - z) * jnp.tanh(xn + r * (hn + cell["hn"]["bias"])) + z * h
        return h, h

    states = jax.lax.scan(step, jnp.zeros((*obs.shape[1:-1], policy.hidden), jnp.float32), projected)[1]
    return policy.apply(params, states, method=RecurrentPolicy.readout)


def _best(fn: object, *args: object, reps: int = 20) -> float:
    """Best wall seconds of ``reps`` calls after a warm-up."""
    import jax

    jax.block_until_ready(fn(*args))
    best = float("inf")
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best


if __name__ == "__main__":  # One process of ``seeds_and_devices`` (nothing may start JAX before the device count).
    parser = argparse.ArgumentParser(description="One process of `make bench`'s seeds section: dil's seconds per "
                                     "iteration at the bandit CPU preset for 1, 2, 4 and 8 seeds with the CPU shown "
                                     "as N devices; run by bench.py, once per device count. With --cells: the GRU's "
                                     "gradient steps against the minGRU's, on one core.")
    parser.add_argument("--devices", type=int, help="CPU devices (the seed axis is split over them)")
    parser.add_argument("--cells", action="store_true", help="time model.cell=gru against mingru instead")
    args = parser.parse_args()
    if args.cells:
        from jaxdeconf.platform import available_cores, pin_to_core

        pin_to_core(available_cores()[0])  # One core, before JAX starts its backend.
        cells()
        sys.exit(0)
    if args.devices is None or args.devices < 1:
        parser.exit(2, f"error: --devices={args.devices} is not allowed: need a positive integer\n")
    devices_one(args.devices)
