# cython: language_level=3
"""Delivery among the nodes of one process, compiled (:class:`canbrake.nodes.group.Router`): a
generation's frames into each node's inbox, and each node's batch handed to it.

Written by hand because it runs for every frame of every generation of the in-process engine and
of each process hosting ECUs (``ecu.per_process``); routes and filters stay Python
(``Router.route``, computed once per identifier), so this only looks them up.
"""
from cpython.dict cimport PyDict_GetItem
from cpython.list cimport PyList_GET_ITEM, PyList_GET_SIZE
from cpython.object cimport PyObject
from cpython.tuple cimport PyTuple_GET_ITEM, PyTuple_GET_SIZE
from canbrake.bus._ring cimport MSG_EXT, MSG_ID, msg_get


def split(list gen, dict routes, object route, Py_ssize_t n):
    """The share of each of ``n`` nodes of the generation ``gen`` of (sender index or -1, frame):
    in order, the frames whose route takes them to the node, its own left out. ``routes``:
    ``identifier << 1 | extended`` -> the indices of the nodes that accept it; ``route(aid,
    extended)`` gives (and caches in ``routes``) one not there yet."""
    cdef list inbox = [[] for _ in range(n)]
    cdef Py_ssize_t i, t, sender
    cdef PyObject* r
    cdef tuple item, targets
    for i in range(PyList_GET_SIZE(gen)):
        item = <tuple>PyList_GET_ITEM(gen, i)
        sender = <object>PyTuple_GET_ITEM(item, 0)
        msg = <object>PyTuple_GET_ITEM(item, 1)
        aid = msg_get(msg, MSG_ID)
        ext = msg_get(msg, MSG_EXT)
        key = (aid << 1) | (1 if ext else 0)
        r = PyDict_GetItem(routes, key)
        targets = route(aid, ext) if r is NULL else <tuple>r
        for t in range(PyTuple_GET_SIZE(targets)):
            idx = <object>PyTuple_GET_ITEM(targets, t)
            if <Py_ssize_t>idx != sender:
                (<list>PyList_GET_ITEM(inbox, <Py_ssize_t>idx)).append(msg)
    return inbox


def hand(object router, list nodes, list handlers, list inbox, double now):
    """Hand each node its batch (``handlers[i]``: its ``handle_batch``, bound once, ``Node.batch_handler``), unless it has
    finished; returns the next generation, (node index, frame) in node order and each node's order
    sent. ``router.current`` names the node being called."""
    cdef list gen = []
    cdef Py_ssize_t i
    cdef list batch, out
    for i in range(PyList_GET_SIZE(inbox)):
        batch = <list>PyList_GET_ITEM(inbox, i)
        if not batch:
            continue
        node = <object>PyList_GET_ITEM(nodes, i)
        router.current = node
        if node.finished:
            continue
        res = (<object>PyList_GET_ITEM(handlers, i))(batch, now)
        if res:
            for m in res:
                gen.append((i, m))
    return gen
