# cython: language_level=3, boundscheck=False, wraparound=False
# distutils: extra_compile_args = -O2 -ffp-contract=off
"""The discrete-event core of :class:`canbrake.bus.timing.BusTimingModel`, compiled.

Per-node transmit queues, arbitration by identifier when the bus goes idle, non-preemptive
transmission, error frames and retransmissions under a fault model, transmit buffers: the
per-frame work of the timing model (every frame of every period of a ``bus.timing: model`` run,
in every node that replicates the model). :class:`EventCore` is the base class of
``BusTimingModel``; statistics (bus load, latency percentiles) stay in Python over the history
lists kept here.

Written by hand because no library models CAN arbitration or bus time (python-can and cantools
stop at frames; see :mod:`canbrake.bus.timing`). The three priority queues (frames not yet due,
each node's queue, the heads of the node queues) are binary heaps of :class:`Pending` ordered by
C-level keys instead of Python tuples: the arbitration field as one integer (:func:`arb_key`, the
same order as the bit-by-bit comparison on the wire), then the queue time, then the submission
number. Every key is unique (the submission number), so the order of events is the one of any
correct priority queue, hence of the former ``heapq`` implementation.

Floating point: ``-ffp-contract=off`` keeps ``a + b / c`` two roundings as in Python, so the
times are bit-identical to the interpreter's arithmetic.
"""
from libc.math cimport isfinite, INFINITY

#: time tolerance (s), see canbrake.bus.timing.TIME_EPS_S
cdef double TIME_EPS_S = 1e-12
cdef int IFS_BITS = 3


cpdef unsigned long long arb_key(long long arbitration_id, bint is_extended, bint is_remote):
    """The arbitration field as one integer, smaller wins: base ID (11 bits), then standard RTR /
    extended SRR (recessive), IDE (standard wins), the 18-bit ID extension, the extended RTR —
    the bit-by-bit order on the wire (a data frame beats a remote frame of the same ID)."""
    cdef unsigned long long rtr = 1 if is_remote else 0
    cdef unsigned long long a = <unsigned long long>arbitration_id
    if is_extended:
        return ((a >> 18) << 21) | (1ULL << 20) | (1ULL << 19) | ((a & 0x3FFFF) << 1) | rtr
    return (a << 21) | (rtr << 20)


cdef class Ticket:
    """Receipt for one submitted frame; ``seq`` is unique and increasing per model."""

    cdef readonly long long seq
    cdef readonly object node
    cdef readonly long long arbitration_id
    cdef readonly bint is_extended
    cdef readonly long long bits
    cdef readonly double t_queue_s

    def __init__(self, long long seq, node, long long arbitration_id, bint is_extended, long long bits,
                 double t_queue_s):
        self.seq = seq
        self.node = node
        self.arbitration_id = arbitration_id
        self.is_extended = is_extended
        self.bits = bits
        self.t_queue_s = t_queue_s

    def _astuple(self):
        return (self.seq, self.node, self.arbitration_id, self.is_extended, self.bits, self.t_queue_s)

    def __eq__(self, other):
        if not isinstance(other, Ticket):
            return NotImplemented
        return self._astuple() == (<Ticket>other)._astuple()

    def __hash__(self):
        return hash(self._astuple())

    def __repr__(self):
        return ("Ticket(seq=%r, node=%r, arbitration_id=%r, is_extended=%r, bits=%r, t_queue_s=%r)"
                % self._astuple())


cdef class Delivery:
    """One frame that went over the bus. Times in simulated seconds.

    ``t_start_s`` is the start of its SOF (it won arbitration), ``t_end_s`` the end of its
    transmission (``bits`` bit times later, IFS included if the model counts it). ``dropped``:
    never sent, its node went bus-off or its buffer was full (``t_start_s = t_end_s`` = drop time).
    """

    cdef readonly Ticket ticket
    cdef readonly object node
    cdef readonly long long arbitration_id
    cdef readonly bint is_extended
    cdef readonly bint is_remote
    cdef readonly int dlc
    cdef readonly object data
    cdef readonly long long bits
    cdef readonly double t_queue_s
    cdef readonly double t_start_s
    cdef readonly double t_end_s
    cdef readonly object tag
    cdef readonly bint dropped

    def __init__(self, Ticket ticket, node, long long arbitration_id, bint is_extended, bint is_remote, int dlc,
                 data, long long bits, double t_queue_s, double t_start_s, double t_end_s, tag=None,
                 bint dropped=False):
        self.ticket = ticket
        self.node = node
        self.arbitration_id = arbitration_id
        self.is_extended = is_extended
        self.is_remote = is_remote
        self.dlc = dlc
        self.data = data
        self.bits = bits
        self.t_queue_s = t_queue_s
        self.t_start_s = t_start_s
        self.t_end_s = t_end_s
        self.tag = tag
        self.dropped = dropped

    @property
    def latency_s(self):
        """End of transmission minus time queued (s)."""
        return self.t_end_s - self.t_queue_s

    @property
    def queueing_delay_s(self):
        """Time spent waiting for the bus (s): start minus time queued."""
        return self.t_start_s - self.t_queue_s

    def _astuple(self):
        return (self.ticket, self.node, self.arbitration_id, self.is_extended, self.is_remote, self.dlc, self.data,
                self.bits, self.t_queue_s, self.t_start_s, self.t_end_s, self.tag, self.dropped)

    def __eq__(self, other):
        if not isinstance(other, Delivery):
            return NotImplemented
        return self._astuple() == (<Delivery>other)._astuple()

    def __hash__(self):
        return hash(self._astuple())

    def __repr__(self):
        return ("Delivery(ticket=%r, node=%r, arbitration_id=%r, is_extended=%r, is_remote=%r, dlc=%r, data=%r, "
                "bits=%r, t_queue_s=%r, t_start_s=%r, t_end_s=%r, tag=%r, dropped=%r)" % self._astuple())


cdef inline Delivery _delivery(Pending p, double t_start, double t_end, bint dropped):
    cdef Delivery d = Delivery.__new__(Delivery)
    cdef Ticket tk = p.ticket
    d.ticket = tk
    d.node = tk.node
    d.arbitration_id = tk.arbitration_id
    d.is_extended = tk.is_extended
    d.is_remote = p.is_remote
    d.dlc = p.dlc
    d.data = p.data
    d.bits = tk.bits
    d.t_queue_s = tk.t_queue_s
    d.t_start_s = t_start
    d.t_end_s = t_end
    d.tag = p.tag
    d.dropped = dropped
    return d


cdef class Pending:
    """A submitted frame. ``bus_key`` orders arbitration between nodes, ``node_key`` the node's own
    queue (priority or FIFO); ``queue`` is its node's queue once it joined it."""

    cdef readonly Ticket ticket
    cdef readonly bint is_remote
    cdef readonly int dlc
    cdef readonly object data
    cdef readonly object tag
    cdef unsigned long long akey
    cdef double tq
    cdef long long seq
    cdef bint fifo
    cdef list queue

    @property
    def bus_key(self):
        return (self.akey, self.tq, self.seq)

    @property
    def node_key(self):
        if self.fifo:
            return (self.tq, self.seq)
        return (self.akey, self.tq, self.seq)


# -- binary heaps of Pending over Python lists --------------------------------------------------
# mode 0: by (t_queue, seq) (frames not yet due, FIFO node queues); mode 1: by (arbitration key,
# t_queue, seq) (priority node queues, the heads of the node queues).

cdef inline bint _lt(Pending a, Pending b, int mode):
    if mode == 1 and a.akey != b.akey:
        return a.akey < b.akey
    if a.tq != b.tq:
        return a.tq < b.tq
    return a.seq < b.seq


cdef void _push(list h, Pending p, int mode):
    h.append(p)
    cdef Py_ssize_t pos = len(h) - 1, parent
    cdef Pending q
    while pos > 0:
        parent = (pos - 1) >> 1
        q = <Pending>h[parent]
        if _lt(p, q, mode):
            h[pos] = q
            pos = parent
        else:
            break
    h[pos] = p


cdef Pending _pop(list h, int mode):
    cdef Pending last = <Pending>h.pop()
    cdef Pending top, c
    cdef Py_ssize_t n = len(h), pos = 0, child
    if n == 0:
        return last
    top = <Pending>h[0]
    while True:
        child = 2 * pos + 1
        if child >= n:
            break
        if child + 1 < n and _lt(<Pending>h[child + 1], <Pending>h[child], mode):
            child += 1
        c = <Pending>h[child]
        if _lt(c, last, mode):
            h[pos] = c
            pos = child
        else:
            break
    h[pos] = last
    return top


cdef class EventCore:
    """Queues, arbitration and transmission of :class:`canbrake.bus.timing.BusTimingModel` (its
    base class; the arguments are checked there)."""

    cdef public double bitrate_bps
    cdef public object stuffing
    cdef public object queue_policy
    cdef public bint include_ifs
    cdef public bint record_history
    cdef public object faults
    cdef public list _future
    cdef public dict _ready
    cdef public long long _n_ready
    cdef public list _heads
    cdef public dict _bits_memo
    cdef public long long _seq
    cdef public double _now
    cdef public double _bus_free_at
    cdef public list _committed
    cdef public list _busy_start, _busy_end, _offered_t, _offered_dur
    cdef public dict _lat, _lat_node
    cdef public list _dropped
    cdef public list _buffer_cfgs
    cdef public dict _buffers, _buffer_of
    cdef bint _fifo

    def __init__(self, double bitrate_bps, stuffing, queue_policy, bint include_ifs, bint record_history, faults,
                 tx_buffers):
        self.bitrate_bps = bitrate_bps
        self.stuffing = stuffing
        self.queue_policy = queue_policy
        self._fifo = queue_policy == "fifo"
        self.include_ifs = include_ifs
        self.record_history = record_history
        self._future = []  # not yet queued, by (t_queue, seq)
        self._ready = {}  # node -> its queue, by node_key
        self._n_ready = 0
        # the heads of the node queues by bus_key (an entry whose frame is no longer its queue's
        # head is stale and skipped): arbitration in O(log nodes) instead of a scan of every node
        self._heads = []
        self._bits_memo = {}  # frame lengths without payload (submit)
        self._seq = 0
        self._now = -INFINITY
        self._bus_free_at = -INFINITY
        self._committed = []  # started, not yet handed out by advance()
        self._busy_start = []
        self._busy_end = []
        self._offered_t = []
        self._offered_dur = []
        self._lat = {}
        self._lat_node = {}
        self.faults = faults
        if faults is not None:
            faults.bitrate_bps = self.bitrate_bps
        self._dropped = []
        self._buffer_cfgs = list(tx_buffers or [])
        self._buffers = {}  # node -> TxBuffer, for nodes with a configured buffer
        self._buffer_of = {}  # node -> TxBuffer or None (cache)

    # -- input ------------------------------------------------------------------------------
    def submit(self, node, msg_id, is_extended, dlc, data=None, t_queue_s=0.0, *, is_remote=False, tag=None):
        """Queue one frame at ``node`` at simulated time ``t_queue_s`` (s).

        ``data`` may be None unless ``stuffing="actual"``. ``tag`` is any object handed back in
        the :class:`Delivery` (e.g. the ``can.Message`` or ``TxFrame``).
        """
        if not isinstance(node, str) or not node:
            raise ValueError(f"node must be a non-empty string, got {node!r}")
        t_q = float(t_queue_s)
        if not isfinite(t_q):
            raise ValueError(f"t_queue_s must be a finite time in seconds, got {t_queue_s!r}")
        payload = None if data is None else bytes(data)
        return self._submit(node, msg_id, is_extended, dlc, payload, t_q, is_remote, tag)

    cdef Ticket _submit(self, node, msg_id, is_extended, dlc, payload, double t_q, is_remote, tag):
        if t_q < self._now - TIME_EPS_S:
            raise ValueError(f"t_queue_s={t_q!r} is before the model's current time "
                             f"now_s={self._now!r}: the bus has already been simulated past it")
        if payload is None and self.stuffing != "actual" and type(msg_id) is int and type(dlc) is int:
            # the nominal schedule submits the same few frames every period: their length is
            # checked and computed once (plain ints only: anything else takes frame_bits' checks)
            key = (msg_id, bool(is_extended), dlc, bool(is_remote))
            bits = self._bits_memo.get(key)
            if bits is None:
                from canbrake.bus.timing import frame_bits
                bits = self._bits_memo[key] = frame_bits(msg_id, is_extended, dlc, None, self.stuffing,
                                                         is_remote=is_remote, include_ifs=self.include_ifs)
        else:
            from canbrake.bus.timing import frame_bits
            bits = frame_bits(msg_id, is_extended, dlc, payload, self.stuffing,
                              is_remote=is_remote, include_ifs=self.include_ifs)
        cdef Ticket tk = Ticket.__new__(Ticket)
        tk.seq = self._seq
        tk.node = node
        tk.arbitration_id = msg_id
        tk.is_extended = is_extended
        tk.bits = bits
        tk.t_queue_s = t_q
        if self.faults is not None:
            self.faults.register(node)
        self._seq += 1
        cdef Pending p = Pending.__new__(Pending)
        p.ticket = tk
        p.is_remote = is_remote
        p.dlc = dlc
        p.data = payload
        p.tag = tag
        p.akey = arb_key(tk.arbitration_id, tk.is_extended, p.is_remote)
        p.tq = t_q
        p.seq = tk.seq
        p.fifo = self._fifo
        _push(self._future, p, 0)
        if self.record_history:
            self._offered_t.append(t_q)
            self._offered_dur.append(tk.bits / self.bitrate_bps)
        return tk

    def submit_streams(self, long long k, double t, list senders, list ids, list exts, list dlcs, list offsets,
                       list every, dict drift):
        """Queue the frames of tick ``k`` (start ``t``, s) of a nominal schedule given column-wise:
        stream i (``senders[i]`` sends ``ids[i]``, ``exts[i]``, ``dlcs[i]`` bytes every ``every[i]``
        ticks at ``t + offsets[i]`` plus its sender's clock offset ``drift``) is queued if ``k`` is a
        multiple of its ``every``, tagged ``(k, sender, id)`` (:class:`canbrake.bus.schedule.LockstepBusTiming`)."""
        cdef Py_ssize_t i, n = len(senders)
        cdef long long e
        for i in range(n):
            e = every[i]
            if k % e == 0:
                s = senders[i]
                mid = ids[i]
                self._submit(s, mid, exts[i], dlcs[i], None, t + <double>offsets[i] + <double>drift.get(s, 0.0),
                             False, (k, s, mid))

    # -- simulation -------------------------------------------------------------------------
    def next_event_s(self):
        """Earliest instant (s) at which anything can happen on this bus: a queued frame that may
        start, a frame that ends, a submission that becomes due; ``math.inf`` if none. Nothing is
        delivered before it (used to co-simulate several buses, :mod:`canbrake.bus.segments`)."""
        cdef double t = INFINITY
        cdef Delivery d
        if self._n_ready:
            t = max(self._bus_free_at, self._now)
        if self._future:
            t = min(t, (<Pending>self._future[0]).tq)
        for d in self._committed:
            t = min(t, d.t_end_s)
        return t

    def _buffer(self, node):
        b = self._buffer_of.get(node, False)
        if b is False:
            from canbrake.bus.txbuffer import make_tx_buffer

            cfg = next((c for c in self._buffer_cfgs if c.applies_to(node)), None)
            b = None if cfg is None else make_tx_buffer(cfg)
            self._buffer_of[node] = b
            if b is not None:
                self._buffers[node] = b
        return b

    def advance(self, until_s):
        """Simulate the bus up to ``until_s`` (s); return frames whose transmission ended by then.

        Deliveries come in bus order (increasing ``t_end_s``). A frame that has started but not
        finished by ``until_s`` is returned by a later call.
        """
        cdef double until = float(until_s)
        if not isfinite(until):
            raise ValueError(f"until_s must be a finite time in seconds, got {until_s!r}")
        if until < self._now - TIME_EPS_S:
            raise ValueError(f"until_s={until!r} is before now_s={self._now!r}; time only moves on")
        until = max(until, self._now)
        cdef list future = self._future, heads = self._heads, q, best_q
        cdef dict ready = self._ready
        cdef double t, limit
        cdef Pending p, hp, bestp
        cdef object fc = self.faults
        cdef bint has_buffers = len(self._buffer_cfgs) > 0
        while True:
            t = self._bus_free_at
            if not self._n_ready:
                if not future:
                    break
                t = max(t, (<Pending>future[0]).tq)
            if t >= until - 2 * TIME_EPS_S:
                break
            if fc is not None:
                fc.idle(self._bus_free_at, t)
            # everything queued by t (within rounding) joins its node's queue ...
            limit = t + TIME_EPS_S
            while future and (<Pending>future[0]).tq <= limit:
                p = _pop(future, 0)
                node = p.ticket.node
                if fc is not None and fc.is_bus_off(node):
                    self._drop(p, t)
                    continue
                if has_buffers:
                    b = self._buffer(node)
                    if b is not None:
                        lost = b.push(p)
                        if lost is not None:
                            self._drop(<Pending>lost, t)
                        else:
                            self._n_ready += 1
                        continue
                q = ready.get(node)
                if q is None:
                    q = ready[node] = []
                self._enqueue(q, p)
                self._n_ready += 1
            # ... and the heads of the node queues arbitrate
            best_q = None
            bestp = None
            while heads:
                hp = <Pending>heads[0]
                if hp.queue and hp.queue[0] is hp:
                    best_q, bestp = hp.queue, hp
                    break
                _pop(heads, 1)  # stale: sent, or its node's queue has a new head or was dropped
            best_b = None
            if has_buffers:
                for b in self._buffers.values():
                    h = b.head()
                    if h is not None and (bestp is None or _lt(<Pending>h, bestp, 1)):
                        best_b, bestp = b, <Pending>h
            if best_b is not None:
                p = <Pending>best_b.pop_head()
                queue = best_b
            elif best_q is None:  # everything that was due belonged to bus-off nodes
                continue
            else:
                p = _pop(best_q, 0 if self._fifo else 1)
                if best_q:  # the node's next frame is its new head
                    _push(heads, <Pending>best_q[0], 1)
                queue = best_q
            self._n_ready -= 1
            if fc is None:
                self._transmit(p, t)
            else:
                self._attempt(p, t, queue)
        if self.faults is not None:
            self.faults.idle(self._bus_free_at, until)
        self._now = until
        cdef list done = [], rest = []
        cdef Delivery d
        for d in self._committed:
            if d.t_end_s <= until:
                done.append(d)
            else:
                rest.append(d)
        if done:
            self._committed = rest
            if self.record_history:
                for d in done:
                    self._lat.setdefault((d.arbitration_id, d.is_extended), []).append(d.t_end_s - d.t_queue_s)
                    self._lat_node.setdefault((d.arbitration_id, d.is_extended, d.node),
                                              []).append(d.t_end_s - d.t_queue_s)
        return done

    def advance_into(self, until_s, dict done, log):
        """:meth:`advance`, then per frame carried: ``(t_end_s, arbitration_id, is_extended)`` appended
        to ``log`` (unless None) and ``done[tag] = t_end_s`` for tags ``(k, sender, id)`` with
        ``id >= 0``; frames dropped (bus-off, full buffer) get ``done[tag] = inf``
        (:class:`canbrake.bus.schedule.LockstepBusTiming`)."""
        cdef Delivery d
        for d in self.advance(until_s):
            if log is not None:
                log.append((d.t_end_s, d.arbitration_id, d.is_extended))
            tag = d.tag
            if tag[2] >= 0:
                done[tag] = d.t_end_s
        if self.faults is not None or self._buffer_cfgs:  # frames of bus-off nodes / full buffers
            for d in self.pop_dropped():
                if d.tag[2] >= 0:
                    done[d.tag] = INFINITY

    cdef void _enqueue(self, list q, Pending p):
        """Put ``p`` in its node's queue ``q``; if it is the queue's new head, in the heads' heap."""
        p.queue = q
        _push(q, p, 0 if p.fifo else 1)
        if q[0] is p:
            _push(self._heads, p, 1)

    cdef void _drop(self, Pending p, double t):
        self._dropped.append(_delivery(p, t, t, True))

    def pop_dropped(self):
        """Frames dropped because their node was bus-off or its buffer full (since the last call),
        in drop order."""
        out, self._dropped = self._dropped, []
        return out

    cdef _attempt(self, Pending p, double t_start, queue):
        """One transmission attempt under the fault model: success, or an error frame and a
        retransmission (or, if the sender went bus-off, the loss of its whole queue)."""
        from canbrake.bus.faults import ERROR_FRAME_BITS, ErrorEvent

        fc = self.faults
        cdef Ticket tk = p.ticket
        cdef int ifs = IFS_BITS if self.include_ifs else 0
        hit = fc.draw(tk.node, tk.bits - ifs, t_start)
        if hit is None:
            self._transmit(p, t_start)
            fc.frame_end(self._bus_free_at)
            fc.tx_ok(tk.node, self._bus_free_at)
            return
        bit, cause = hit
        cdef double t_end = t_start + (bit + 1 + ERROR_FRAME_BITS + ifs) / self.bitrate_bps
        self._bus_free_at = t_end
        if self.record_history:
            self._busy_start.append(t_start)
            self._busy_end.append(t_end)
        fc.frame_end(t_end)
        c = fc.tx_error(tk.node, t_end)
        fc.events.append(ErrorEvent(t_start, t_end, tk.node, tk.arbitration_id, tk.is_extended, bit, cause,
                                    c.tec, c.state))
        cdef list ql
        if c.state == "bus_off":
            self._drop(p, t_end)
            if isinstance(queue, list):
                ql = queue
                while ql:
                    self._drop(_pop(ql, 0 if p.fifo else 1), t_end)
                    self._n_ready -= 1
            else:  # a TxBuffer
                for x in queue.drain():
                    self._drop(<Pending>x, t_end)
                    self._n_ready -= 1
        elif isinstance(queue, list):
            self._enqueue(queue, p)  # automatic retransmission
            self._n_ready += 1
        else:
            queue.requeue(p)
            self._n_ready += 1

    cdef void _transmit(self, Pending p, double t_start):
        cdef double t_end = t_start + p.ticket.bits / self.bitrate_bps
        self._bus_free_at = t_end
        self._committed.append(_delivery(p, t_start, t_end, False))
        if self.record_history:
            self._busy_start.append(t_start)
            self._busy_end.append(t_end)
