"""LIF pooling kernel: event stream -> time steps -> spiking pooling -> event stream.

The kernel runs exactly the arithmetic of :class:`~evdown_torch.models.SpikingPooling`
(``snntorch.Leaky``) on the time steps that hold events, with the membrane kept as one float32
vector of ``2 * Ho * Wo`` neurons, and jumps over the steps in between:

- the input current of a step is a scatter-add of its events into ``(polarity, region)``,
  computed for a chunk of active steps (and of events) at a time, so memory follows the chunk
  and the number of active steps, never ``T x H x W`` nor ``T x Ho x Wo`` over the recording;
- over ``g`` empty steps a membrane at or below threshold only decays, by ``beta ** g``; a
  membrane above threshold keeps firing there (snntorch's reset acts one step later and
  subtract removes one threshold per step), so those neurons are stepped through the empty
  steps one by one, with the module's arithmetic, until they stop firing. That loop runs once
  per step that emits a spike, so the cost follows the active steps plus the output.

The spikes equal those of the module run on the dense binned stream, step by step; the only
difference is that ``beta ** g`` is one rounding where stepping applies ``g`` (bit-identical
when ``beta`` is 0, 1 or a power of two), which changes a spike only if a membrane lands within
float32 rounding of the threshold.
"""

from __future__ import annotations

import torch
from torch import Tensor

from evdown_torch._tensors import divide, region_xy, sort_by_time
from evdown_torch.events import Events

__all__ = ["active_steps", "lif_pooling", "step_end_time", "step_index"]

#: Dense per-chunk work is at most this many (step, neuron) cells (two 4 MiB float32 buffers).
DEFAULT_CHUNK_CELLS = 1 << 20
#: A chunk holds at most this many input events (at least one whole step).
DEFAULT_CHUNK_EVENTS = 1 << 20


def step_index(relative_t: Tensor, dt: float) -> Tensor:
    """Time step of each event, ``floor((t - t_start) / dt)``, as int64.

    Args:
        relative_t: ``(N,)`` ``t - t_start``, int64 or float64, non-negative.
        dt: step length in the stream's time unit.

    Returns:
        ``(N,)`` int64 step indices (exact integer division when ``t`` is an integer and ``dt``
        a whole number).
    """
    if not relative_t.is_floating_point() and float(dt).is_integer():
        return torch.div(relative_t, int(dt), rounding_mode="floor")
    return torch.floor(relative_t.to(torch.float64) / dt).to(torch.int64)


def active_steps(
    t: Tensor, *, t_start: Tensor, dt: float, block: int
) -> tuple[Tensor, Tensor]:
    """The steps that hold events and their event counts, for sorted timestamps.

    Works through ``t`` in blocks of ``block`` events, so that no per-event step index of the
    whole stream is ever held.

    Returns:
        ``(active, counts)``: ``(A,)`` int64 increasing step indices and ``(A,)`` int64 counts.
    """
    actives, counts = [], []
    last = None
    for b0 in range(0, t.shape[0], block):
        steps = step_index(t[b0 : b0 + block] - t_start, dt)
        active, count = torch.unique_consecutive(steps, return_counts=True)
        if last is not None and int(active[0]) == last:  # a step across two blocks
            counts[-1][-1:] += count[0]
            active, count = active[1:], count[1:]
        if active.numel():
            # clone: unique_consecutive's results may keep the block-sized storage alive
            actives.append(active.clone())
            counts.append(count.clone())
            last = int(active[-1])
    return torch.cat(actives), torch.cat(counts)


def step_end_time(steps: Tensor, *, t_start: Tensor, t_end: Tensor, dt: float) -> Tensor:
    """Output timestamp ``t_start + (k + 1) * dt`` of steps ``k``, clipped to ``t_end``.

    Integer timestamps stay int64: with a whole ``dt`` the sum is exact; otherwise the offset
    ``(k + 1) * dt`` is rounded to the nearest integer, halves upward, before it is added.
    """
    if not t_start.is_floating_point():
        if float(dt).is_integer():
            offset = (steps + 1) * int(dt)
        else:
            offset = torch.floor((steps + 1).to(torch.float64) * dt + 0.5).to(torch.int64)
    else:
        offset = (steps + 1).to(torch.float64) * dt
    return torch.minimum(t_start + offset, t_end)


def _nonzero_flat(values: Tensor, mask: Tensor) -> Tensor:
    """Increasing flat indices of the nonzero entries of a contiguous tensor of sparse 0/1.

    Same as ``values.reshape(-1).nonzero()[:, 0]``, several times faster on CPU for sparse
    input: the bool mask is scanned 8 entries (one int64 word) at a time.

    Args:
        values: the tensor, ``n`` entries.
        mask: a bool workspace of at least ``n`` entries rounded up to a multiple of 8.
    """
    n = values.numel()
    words = -(-n // 8)
    mask = mask[: 8 * words]
    mask[n:] = False
    mask[:n].copy_(values.reshape(-1))
    hit_words = mask.view(torch.int64).nonzero()[:, 0]
    hits = mask.view(words, 8)[hit_words].nonzero()
    return hit_words[hits[:, 0]] * 8 + hits[:, 1]


class _Neurons:
    """The membrane of all neurons and snntorch.Leaky's update, on a flat float32 vector.

    Every operation is the one snntorch.Leaky performs, in the same order and dtype (0-dim
    float32 constants), so the membrane is bit-identical to the module's.
    """

    def __init__(
        self, count: int, *, beta: float, threshold: float, reset_mechanism: str, device
    ) -> None:
        self.beta = torch.tensor(beta, dtype=torch.float32, device=device)
        self.threshold = torch.tensor(threshold, dtype=torch.float32, device=device)
        self.beta_value = float(self.beta)
        self.threshold_value = float(self.threshold)  # exactly the float32 value
        self.reset = reset_mechanism
        self.mem = torch.zeros(count, dtype=torch.float32, device=device)
        # R = [U_{k-1} > threshold] as float 0/1 (snntorch's reset signal): a view of the last
        # step's row of spikes, or one of these two buffers.
        self.fired = torch.zeros(count, dtype=torch.float32, device=device)
        self._gap_fired = torch.zeros_like(self.fired)
        self._carried = self.fired

    def detach_from_spikes(self) -> None:
        """Copy ``fired`` out of the spike rows, before they are reused."""
        if self.fired is not self._carried:
            self._carried.copy_(self.fired)
            self.fired = self._carried

    def step(self, current: Tensor, spikes_out: Tensor) -> None:
        """One step with input ``current``; writes ``U_k > threshold`` (0/1) to ``spikes_out``."""
        mem, reset = self.mem, self.fired
        if self.reset == "zero":
            mem.addcmul_(mem, reset, value=-1.0)  # (1 - R) U: U - U = +0 or U - 0 = U, exact
        torch.mul(self.beta, mem, out=mem)
        mem.add_(current)
        if self.reset == "subtract":
            mem.sub_(reset, alpha=self.threshold_value)  # - R * threshold, an exact product
        torch.gt(mem, self.threshold, out=spikes_out)
        self.fired = spikes_out

    def skip(self, gap: int, first_step: int) -> tuple[Tensor, Tensor] | None:
        """Advance through ``gap`` steps without input.

        Returns:
            ``(steps, neurons)`` of the spikes emitted in those steps (the first one being
            ``first_step``), or ``None`` when there are none.
        """
        firing = self.fired.nonzero().squeeze(1)
        above = self.mem[firing]
        self.mem.mul_(self.beta_value**gap)  # U <= threshold: it only decays
        self.fired = self._gap_fired.zero_()
        if firing.numel() == 0:
            return None
        if self.reset == "zero":  # reset to zero, then no input: nothing more to emit
            self.mem[firing] = 0.0
            return None
        if self.reset == "none" and self.beta_value == 1.0:  # fires in every empty step
            self.mem[firing] = above
            self.fired[firing] = 1.0
            steps = torch.arange(first_step, first_step + gap, device=firing.device)
            return steps.repeat_interleave(firing.numel()), firing.repeat(gap)
        out_steps, out_neurons = [], []
        j = 0
        while firing.numel() and j < gap:  # each pass emits at least one spike
            j += 1
            above = self.beta * above  # plus a zero current: exact
            if self.reset == "subtract":
                above = above - self.threshold
            spiking = above > self.threshold
            out_neurons.append(firing[spiking])
            out_steps.append(torch.full_like(out_neurons[-1], first_step + j - 1))
            quiet = ~spiking
            self.mem[firing[quiet]] = above[quiet] * self.beta_value ** (gap - j)
            firing, above = firing[spiking], above[spiking]
        if firing.numel():  # still firing at the end of the gap
            self.mem[firing] = above
            self.fired[firing] = 1.0
        return torch.cat(out_steps), torch.cat(out_neurons)


def lif_pooling(
    events: Events,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    dt: float,
    beta: float,
    threshold: float,
    weight: float,
    mutual_inhibition: float = 0.0,
    reset_mechanism: str = "subtract",
    chunk_cells: int = DEFAULT_CHUNK_CELLS,
    chunk_events: int = DEFAULT_CHUNK_EVENTS,
) -> Events:
    """Downscale a stream through one leaky integrate-and-fire neuron per region and polarity.

    The stream is binned into steps of ``dt`` from ``t_start`` (its first timestamp); the
    events of a step are pooled as :class:`~evdown_torch.models.SpikingPooling` pools a
    ``ToFrame`` tensor (weight ``+weight`` from the same polarity, ``-mutual_inhibition`` from
    the other), then ``snntorch.Leaky`` semantics run over every step from 0 to the step of
    ``t_end``. A spike of the neuron of polarity ``c`` and region ``(i, j)`` in step ``k``
    becomes the event ``(x=j, y=i, t=t_start + (k + 1) * dt clipped to t_end, p=c)``.

    Args:
        events: ``N`` events (any order); ``t`` int64 or float64.
        sensor_size: input sensor ``(W, H, P)``.
        factor: ``(fx, fy)``, positive integers.
        dt: step length, in the unit of ``t`` (microseconds for Tonic), positive.
        beta: membrane decay per step in ``[0, 1]`` (``exp(-dt / tau)``).
        threshold: firing threshold, positive (fires when the membrane exceeds it).
        weight: weight of each same-polarity input event, positive.
        mutual_inhibition: weight of each opposite-polarity input event, subtracted, ``>= 0``.
        reset_mechanism: ``"subtract"``, ``"zero"`` or ``"none"``.
        chunk_cells: at most this many ``(active step, neuron)`` cells are dense at once.
        chunk_events: at most about this many events are processed at once (whole steps).

    Returns:
        Output events sorted by ``t`` (within a step: OFF before ON, then row-major region),
        ``t`` of the input's dtype, on the input's device.

    Example:
        >>> ev = Events.from_columns([0, 1, 0, 1, 3], [0, 0, 1, 1, 0], [0, 1, 2, 3, 9],
        ...                          [1, 1, 1, 1, 0])
        >>> out = lif_pooling(ev, sensor_size=(4, 2, 2), factor=(2, 2), dt=2, beta=1.0,
        ...                   threshold=1.0, weight=0.3)
        >>> out.x.tolist(), out.y.tolist(), out.t.tolist(), out.p.tolist()
        ([0], [0], [4], [True])
    """
    events = sort_by_time(events)
    device = events.device
    if events.num_events == 0:
        return Events.empty(events.t.dtype, device)
    fx, fy = factor
    wo, ho = -(-sensor_size[0] // fx), -(-sensor_size[1] // fy)
    plane = wo * ho
    count = 2 * plane
    t_start, t_end = events.t[0], events.t[-1]
    active, per_step = active_steps(events.t, t_start=t_start, dt=dt, block=chunk_events)
    step_end = torch.cumsum(per_step, 0)
    step_begin = step_end - per_step
    active_list = active.tolist()
    begin_list, end_list = step_begin.tolist(), step_end.tolist()
    n_active = len(active_list)

    dtype = torch.float32
    weight_t = torch.tensor(weight, dtype=dtype, device=device)
    inhibition = mutual_inhibition != 0
    inhibition_t = torch.tensor(mutual_inhibition, dtype=dtype, device=device)
    neurons = _Neurons(
        count, beta=beta, threshold=threshold, reset_mechanism=reset_mechanism, device=device
    )
    max_steps = max(1, min(chunk_cells // count, n_active))
    cells = max_steps * count
    # Workspaces, allocated once: a long recording churns no large allocations.
    pooled = torch.empty(cells, dtype=dtype, device=device)
    spikes = torch.empty(max_steps, count, dtype=dtype, device=device)
    mask = torch.empty(-(-cells // 8) * 8, dtype=torch.bool, device=device)
    inhibit = torch.empty(max_steps, 2, plane, dtype=dtype, device=device) if inhibition else None
    capacity = min(chunk_events, events.num_events)
    key = torch.empty(capacity, dtype=torch.int64, device=device)
    part = torch.empty(capacity, dtype=torch.int64, device=device)
    ones = torch.ones(capacity, dtype=dtype, device=device)
    out_steps, out_neurons = [], []
    previous = -1
    a0 = 0
    while a0 < n_active:
        a1 = min(a0 + max_steps, n_active)
        if end_list[a1 - 1] - begin_list[a0] > chunk_events:
            limit = begin_list[a0] + chunk_events
            a1 = max(a0 + 1, int(torch.searchsorted(step_end[a0:a1], limit, right=True)) + a0)
        e0, e1 = begin_list[a0], end_list[a1 - 1]
        rows, size = a1 - a0, e1 - e0
        if size > capacity:  # one step with more events than chunk_events
            capacity = size
            key = torch.empty(size, dtype=torch.int64, device=device)
            part = torch.empty(size, dtype=torch.int64, device=device)
            ones = torch.ones(size, dtype=dtype, device=device)
        # Cell of each event: (active step within the chunk, polarity, region).
        cell, tmp = key[:size], part[:size]
        cell.zero_()
        cell[step_begin[a0 + 1 : a1] - e0] = 1
        torch.cumsum(cell, 0, out=tmp)  # row of the event's step within the chunk
        torch.mul(tmp, count, out=cell)
        divide(events.x[e0:e1], fx, out=tmp)
        cell.add_(tmp)
        divide(events.y[e0:e1], fy, out=tmp)
        cell.add_(tmp, alpha=wo).add_(events.p[e0:e1], alpha=plane)
        # Events per cell, summed exactly in float32 (as the module's sum pooling of counts).
        counts = pooled[: rows * count].zero_()
        counts.index_add_(0, cell, ones[:size])
        counts = counts.view(rows, 2, plane)
        if inhibit is not None:  # w * S - w_inh * S', as the module computes it
            opposite = inhibit[:rows]
            torch.mul(counts[:, 1], inhibition_t, out=opposite[:, 0])
            torch.mul(counts[:, 0], inhibition_t, out=opposite[:, 1])
            counts.mul_(weight_t).sub_(opposite)
        else:  # w * S - 0 * S' == w * S exactly
            counts.mul_(weight_t)
        current = counts.view(rows, count)
        gap_steps, gap_neurons = [], []
        for a in range(a0, a1):
            step = active_list[a]
            gap = step - previous - 1
            if gap > 0:
                emitted = neurons.skip(gap, previous + 1)
                if emitted is not None:
                    gap_steps.append(emitted[0])
                    gap_neurons.append(emitted[1])
            neurons.step(current[a - a0], spikes[a - a0])
            previous = step
        neurons.detach_from_spikes()  # the spike rows are reused by the next chunk
        flat = _nonzero_flat(spikes[:rows], mask)
        cols = flat % count
        step_of_spike = active[a0:a1][torch.div(flat, count, rounding_mode="floor")]
        if gap_steps:
            step_of_spike = torch.cat([step_of_spike, *gap_steps])
            cols = torch.cat([cols, *gap_neurons])
            order = torch.sort(step_of_spike * count + cols).indices
            step_of_spike, cols = step_of_spike[order], cols[order]
        out_steps.append(step_of_spike)
        out_neurons.append(cols)
        a0 = a1

    step_of_spike = torch.cat(out_steps)
    del out_steps
    t = step_end_time(step_of_spike, t_start=t_start, t_end=t_end, dt=dt)
    del step_of_spike
    neuron = torch.cat(out_neurons)
    del out_neurons
    polarity = neuron >= plane
    neuron.add_(polarity, alpha=-plane)  # the region's index in its polarity's plane
    x, y = region_xy(neuron, wo)
    return Events(x, y, t, polarity)
