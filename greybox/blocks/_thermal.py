"""Lumped thermal RC networks (PHYSICS.md §4).

States are temperature rises above ambient [K]. Three concrete blocks:

- `FirstOrderThermal`: the one-node model tau dtheta/dt = R q - theta, parameterised by the
  identifiable pair (time constant [s], thermal resistance [K/W]).
- `ThermalNetwork`: n nodes with heat capacities, conductances to ground and between nodes,
  several heat inputs, optional T^4 radiation (to ambient and between nodes), and optional
  first-order sensor lags that follow chosen nodes without loading them. The 2-node-per-side
  model of PHYSICS.md and the TCLab board are instances of it.
- `ThermalChain`: pad -> beam segments -> anchor, with named scalar capacities and
  resistances (freeable element by element) and an optional elongation lag.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
import numpy as np

STEFAN_BOLTZMANN = 5.670374419e-8  # W/(m^2 K^4)


class AbstractThermal(eqx.Module):
    """A thermal block: `derivative(theta_K, q_W)` and, when linear, `linear_matrices()`."""

    @property
    @abc.abstractmethod
    def n_states(self) -> int: ...

    @property
    @abc.abstractmethod
    def n_inputs(self) -> int: ...

    @property
    @abc.abstractmethod
    def is_linear(self) -> bool: ...

    @abc.abstractmethod
    def derivative(self, theta_K, q_W):
        """d(theta)/dt [K/s] for state `theta_K` (n_states,) and heat inputs `q_W` (n_inputs,)."""

    @abc.abstractmethod
    def linear_matrices(self):
        """(A [1/s], B [K/(J)]) with d(theta)/dt = A theta + B q; only for linear blocks."""


class FirstOrderThermal(AbstractThermal):
    """One node: tau dtheta/dt = R q - theta.

    - `tau_s`: thermal time constant C/G [s].
    - `resistance_K_per_W`: steady-state rise per absorbed watt 1/G [K/W].
    """

    tau_s: float
    resistance_K_per_W: float

    @property
    def n_states(self) -> int:
        return 1

    @property
    def n_inputs(self) -> int:
        return 1

    @property
    def is_linear(self) -> bool:
        return True

    def derivative(self, theta_K, q_W):
        return (self.resistance_K_per_W * q_W - theta_K) / self.tau_s

    def linear_matrices(self):
        a = jnp.reshape(-1.0 / jnp.asarray(self.tau_s), (1, 1))
        b = jnp.reshape(jnp.asarray(self.resistance_K_per_W) / self.tau_s, (1, 1))
        return a, b


def _edge_incidence(couplings, n_nodes):
    """(m, n) matrix D with +1 at the edge's first node and -1 at its second."""
    d = jnp.zeros((len(couplings), n_nodes))
    for e, (i, j) in enumerate(couplings):
        d = d.at[e, i].set(1.0).at[e, j].set(-1.0)
    return d


class ThermalNetwork(AbstractThermal):
    """n-node RC network with heat inputs, optional radiation and sensor lags.

    C_i dtheta_i/dt = sum_k [input_nodes[k] == i] q_k - g0_i theta_i
                      - sum_{edges e=(i,j)} g_e (theta_i - theta_j)
                      - r0_i [(T0 + theta_i)^4 - T0^4] - sum_e r_e [(T0+theta_i)^4 - (T0+theta_j)^4]
    tau_s ds_s/dt = theta_{sensor_nodes[s]} - s_s     (sensor lag, does not load the node)

    - `capacitance_J_per_K` (n,), `ground_conductance_W_per_K` (n,).
    - `couplings`: static tuple of node pairs (i, j); `coupling_conductance_W_per_K` (m,).
    - `input_nodes`: static tuple, the node each heat input enters.
    - `radiation_ground_W_per_K4` (n,) = emissivity * sigma * area per node, and
      `radiation_coupling_W_per_K4` (m,) per edge; `None` means no radiation (linear network).
    - `ambient_K`: ambient temperature [K] (radiation only).
    - `sensor_nodes`: static tuple of nodes followed by a first-order sensor; `sensor_tau_s` (k,).
    State layout: [node rises (n), sensor rises (k)].
    """

    capacitance_J_per_K: jnp.ndarray
    ground_conductance_W_per_K: jnp.ndarray
    coupling_conductance_W_per_K: jnp.ndarray
    couplings: tuple = eqx.field(static=True, default=())
    input_nodes: tuple = eqx.field(static=True, default=(0,))
    radiation_ground_W_per_K4: jnp.ndarray | None = None
    radiation_coupling_W_per_K4: jnp.ndarray | None = None
    ambient_K: float = 296.15
    sensor_nodes: tuple = eqx.field(static=True, default=())
    sensor_tau_s: jnp.ndarray | None = None

    def __check_init__(self):
        n = jnp.shape(self.capacitance_J_per_K)[0]
        if jnp.shape(self.ground_conductance_W_per_K) != (n,):
            raise ValueError("ground_conductance_W_per_K: needs one value per node")
        if jnp.shape(self.coupling_conductance_W_per_K) != (len(self.couplings),):
            raise ValueError("coupling_conductance_W_per_K: needs one value per coupling")
        for node in (
            *self.input_nodes,
            *self.sensor_nodes,
            *(i for e in self.couplings for i in e),
        ):
            if not 0 <= node < n:
                raise ValueError(
                    f"couplings/input_nodes/sensor_nodes: node {node} not in 0..{n - 1}"
                )
        if self.sensor_nodes and jnp.shape(self.sensor_tau_s) != (len(self.sensor_nodes),):
            raise ValueError("sensor_tau_s: needs one time constant per sensor node")

    @property
    def n_nodes(self) -> int:
        return jnp.shape(self.capacitance_J_per_K)[0]

    @property
    def n_states(self) -> int:
        return self.n_nodes + len(self.sensor_nodes)

    @property
    def n_inputs(self) -> int:
        return len(self.input_nodes)

    @property
    def is_linear(self) -> bool:
        return self.radiation_ground_W_per_K4 is None and self.radiation_coupling_W_per_K4 is None

    def _conductance_matrix(self):
        n = self.n_nodes
        k = jnp.diag(jnp.asarray(self.ground_conductance_W_per_K, dtype=float))
        if self.couplings:
            d = _edge_incidence(self.couplings, n)
            k = k + d.T @ (jnp.asarray(self.coupling_conductance_W_per_K)[:, None] * d)
        return k

    def _input_matrix(self):
        e = jnp.zeros((self.n_nodes, self.n_inputs))
        for col, node in enumerate(self.input_nodes):
            e = e.at[node, col].add(1.0)
        return e

    def _radiation_W(self, theta_K):
        """Net radiated power leaving each node [W] (0 if radiation is off)."""
        t0 = self.ambient_K
        fourth = (t0 + theta_K) ** 4
        out = jnp.zeros_like(theta_K)
        if self.radiation_ground_W_per_K4 is not None:
            out = out + self.radiation_ground_W_per_K4 * (fourth - t0**4)
        if self.radiation_coupling_W_per_K4 is not None and self.couplings:
            d = _edge_incidence(self.couplings, self.n_nodes)
            out = out + d.T @ (self.radiation_coupling_W_per_K4 * (d @ fourth))
        return out

    def derivative(self, theta_K, q_W):
        n = self.n_nodes
        nodes = theta_K[:n]
        heat = self._input_matrix() @ jnp.atleast_1d(q_W) - self._conductance_matrix() @ nodes
        if not self.is_linear:
            heat = heat - self._radiation_W(nodes)
        d_nodes = heat / self.capacitance_J_per_K
        if not self.sensor_nodes:
            return d_nodes
        sensors = theta_K[n:]
        d_sensors = (nodes[jnp.array(self.sensor_nodes)] - sensors) / self.sensor_tau_s
        return jnp.concatenate([d_nodes, d_sensors])

    def linear_matrices(self):
        if not self.is_linear:
            raise ValueError(
                "method: the exact ZOH path needs a linear thermal network but radiation is on; "
                "use method='adaptive' (or switch radiation off)"
            )
        return self._matrices(self._conductance_matrix())

    def linearised_matrices(self):
        """(A, B) linearised about theta = 0 (radiation replaced by 4 eps sigma A T0^3)."""
        k = self._conductance_matrix()
        t3 = 4.0 * self.ambient_K**3
        if self.radiation_ground_W_per_K4 is not None:
            k = k + jnp.diag(self.radiation_ground_W_per_K4 * t3)
        if self.radiation_coupling_W_per_K4 is not None and self.couplings:
            d = _edge_incidence(self.couplings, self.n_nodes)
            k = k + d.T @ ((self.radiation_coupling_W_per_K4 * t3)[:, None] * d)
        return self._matrices(k)

    def _matrices(self, k):
        n, ns = self.n_nodes, len(self.sensor_nodes)
        c = jnp.asarray(self.capacitance_J_per_K, dtype=float)
        a = jnp.zeros((n + ns, n + ns)).at[:n, :n].set(-k / c[:, None])
        b = jnp.zeros((n + ns, self.n_inputs)).at[:n].set(self._input_matrix() / c[:, None])
        for s, node in enumerate(self.sensor_nodes):
            a = (
                a.at[n + s, node]
                .set(1.0 / self.sensor_tau_s[s])
                .at[n + s, n + s]
                .set(-1.0 / self.sensor_tau_s[s])
            )
        return a, b


class ThermalChain(AbstractThermal):
    """A linear chain of lumped nodes, each optionally cooled through the air, with an optional
    first-order lag that follows the mean beam rise (PHYSICS.md §4: the two-node pad + beam
    model and its n-node refinement).

    C_i dtheta_i/dt = s_i q - (theta_i - theta_{i+1}) / R_i - theta_i / Ra_i   (theta_n = 0)
    lag_s ds/dt = theta_beam - s,  theta_beam = mean of theta_i over `beam_nodes`

    - `capacity_J_per_K` (n scalars): heat capacity of each node [J/K].
    - `resistance_K_per_W` (n scalars): series resistance from node i to node i + 1; the last
      one joins the last node to the anchor (ambient) [K/W].
    - `air_resistance_K_per_W` (n scalars, or None = no air loss): each node straight to the
      substrate through the air gap [K/W].
    - `lag_s`: time constant of a first-order lag between the mean beam rise and the elongation
      [s]; None = no lag (the elongation follows the beam nodes at once).
    - `heat_share` (static): fraction of the one heat input entering each node; empty = all
      of it into node 0 (a laser-heated pad).
    - `beam_nodes` (static): the nodes whose mean is the mean beam rise; empty = nodes 1..n-1
      (node 0 is the pad), or node 0 when n = 1.

    Every value is a named scalar, so one element can be freed: ``thermal.capacity_J_per_K[1]``.
    State layout: [node rises (n), lag state (1 if `lag_s` is not None)].
    """

    capacity_J_per_K: tuple[float, ...]
    resistance_K_per_W: tuple[float, ...]
    air_resistance_K_per_W: tuple[float, ...] | None = None
    lag_s: float | None = None
    heat_share: tuple[float, ...] = eqx.field(static=True, default=())
    beam_nodes: tuple[int, ...] = eqx.field(static=True, default=())

    def __check_init__(self):
        n = len(self.capacity_J_per_K)
        if n < 1:
            raise ValueError("capacity_J_per_K: needs at least one node")
        if len(self.resistance_K_per_W) != n:
            raise ValueError(
                f"resistance_K_per_W: needs {n} values (node i to i + 1, the last to the anchor)"
            )
        if self.air_resistance_K_per_W is not None and len(self.air_resistance_K_per_W) != n:
            raise ValueError(f"air_resistance_K_per_W: needs {n} values, one per node (or None)")
        if self.heat_share and len(self.heat_share) != n:
            raise ValueError(f"heat_share: needs {n} fractions, one per node (or () for node 0)")
        if any(not 0 <= i < n for i in self.beam_nodes):
            raise ValueError(f"beam_nodes: every node must be in 0..{n - 1}")

    @property
    def n_nodes(self) -> int:
        return len(self.capacity_J_per_K)

    @property
    def n_states(self) -> int:
        return self.n_nodes + (self.lag_s is not None)

    @property
    def n_inputs(self) -> int:
        return 1

    @property
    def is_linear(self) -> bool:
        return True

    def _beam_weights(self):
        n = self.n_nodes
        nodes = self.beam_nodes or (tuple(range(1, n)) if n > 1 else (0,))
        w = np.zeros(n)
        w[list(nodes)] = 1.0 / len(nodes)
        return w

    def _share(self):
        n = self.n_nodes
        return np.asarray(self.heat_share, dtype=float) if self.heat_share else np.eye(n)[0]

    def linear_matrices(self):
        n = self.n_nodes
        c = jnp.stack([jnp.asarray(v, dtype=float) for v in self.capacity_J_per_K])
        g = 1.0 / jnp.stack([jnp.asarray(v, dtype=float) for v in self.resistance_K_per_W])
        ground = jnp.zeros(n).at[n - 1].set(g[n - 1])
        if self.air_resistance_K_per_W is not None:
            ground = ground + 1.0 / jnp.stack(
                [jnp.asarray(v, dtype=float) for v in self.air_resistance_K_per_W]
            )
        k = jnp.diag(ground)
        if n > 1:
            d = np.zeros((n - 1, n))
            d[np.arange(n - 1), np.arange(n - 1)] = 1.0
            d[np.arange(n - 1), np.arange(1, n)] = -1.0
            k = k + d.T @ (g[: n - 1, None] * d)
        a = -k / c[:, None]
        b = (jnp.asarray(self._share()) / c)[:, None]
        if self.lag_s is None:
            return a, b
        rate = 1.0 / jnp.asarray(self.lag_s, dtype=float)
        row = jnp.concatenate([jnp.asarray(self._beam_weights()) * rate, -rate[None]])
        a = jnp.concatenate([jnp.concatenate([a, jnp.zeros((n, 1))], axis=1), row[None]], axis=0)
        return a, jnp.concatenate([b, jnp.zeros((1, 1))], axis=0)

    def derivative(self, theta_K, q_W):
        a, b = self.linear_matrices()
        return a @ theta_K + b @ jnp.reshape(q_W, (-1,))

    def beam_rise_K(self, theta_K):
        """Mean beam rise [K]: the mean of the beam nodes (what heats the beams)."""
        return jnp.asarray(self._beam_weights()) @ theta_K[: self.n_nodes]

    def elongation_rise_K(self, theta_K):
        """The rise the elongation follows [K]: the lag state, or the mean beam rise."""
        return theta_K[self.n_nodes] if self.lag_s is not None else self.beam_rise_K(theta_K)
