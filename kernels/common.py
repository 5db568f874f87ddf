"""What the physics share: the off-grid source/receiver weight (Kaiser-windowed sinc, Hicks 2002, per axis of sum one
and zero first and second moments),
vector loads and stores of contiguous fields, tile boxes, the launch of Warp's generated adjoints, and the
decorator of their kernels (unique_kernel: a kernel's name carries the values its code is generated from).

Physics folders (kernels/<name>/) import from here and from kernels.numerics; nothing here schedules work.
"""

import collections
import functools
import hashlib
import math
import numbers
import re
import types
from dataclasses import dataclass
from typing import Callable

import warp as wp

HICKS_RADIUS = 4


HICKS_B = 6.31


_I0_TERMS = 20


def _i0(x: float) -> float:
    total, term = 1.0, 1.0
    for k in range(1, _I0_TERMS + 1):
        term *= (x / 2.0) ** 2 / k**2
        total += term
    return total


@functools.lru_cache(maxsize=None)
def hicks_weight(dtype):
    """The Warp function of the sources' and receivers' weight per axis in dtype (the acoustic and elastic kernels')."""
    WINDOW_NORM = 1.0 / (_i0(HICKS_B) - 1.0)

    @wp.func
    def hicks(d: dtype) -> dtype:
        # Kaiser-windowed sinc weight at distance d (cells). The window is the Kaiser series written in
        # q = 1 - d^2/r^2 (no square root) minus its edge value, so the weight and its derivative vanish
        # at |d| = r: the operator is C^1 in the position, also for positions on grid nodes.
        q = dtype(1.0) - (d * d) / dtype(wp.static(float(HICKS_RADIUS * HICKS_RADIUS)))
        if q <= dtype(0.0):
            return dtype(0.0)
        pd = dtype(wp.static(math.pi)) * d
        sinc = dtype(1.0) - pd * pd / dtype(6.0)
        if wp.abs(pd) > dtype(1.0e-3):
            # sin(pi d) from the argument reduced by the nearest whole k: exactly 0 at whole d (a point on a node
            # has one weight per axis; sin(pi d) itself gives ~1e-8 in float32 there), same derivative in d
            k = wp.round(d)
            sp = wp.sin(dtype(wp.static(math.pi)) * (d - k))
            if int(k) % 2 != 0:
                sp = -sp
            sinc = sp / pd
        y2 = dtype(wp.static(HICKS_B * HICKS_B / 4.0)) * q
        term = dtype(1.0)
        total = dtype(0.0)
        for k in range(wp.static(_I0_TERMS)):
            term = term * y2 / dtype(wp.static(float((k + 1) * (k + 1))))
            total = total + term
        return sinc * total * dtype(wp.static(WINDOW_NORM))

    return hicks


@functools.lru_cache(maxsize=None)
def hicks_axis(dtype):
    """The Warp function hicks_axis(d, c) of the operator's weight per axis in dtype: the weight of the node at
    distance d (cells) from the position c (cells), among the 2 HICKS_RADIUS nodes of the axis with d in (-r, r].

    w(d) = hicks(d) / sum(hicks) + g(d) (a0 + a1 d + a2 d^2): the windowed sinc divided by its sum over the axis's
    nodes (alone it sums to 1 + 1.3e-3 halfway between nodes), plus the least change, in the norm sum(dw^2 / g), that
    makes the weights' first and second moments sum w d and sum w d^2 zero while keeping their sum one: so the operator
    reproduces fields up to quadratic ones, and its response is flat at the signal's wavenumbers (the normalised sinc's
    second moment, 0.019 cells^2 halfway between nodes, lowered a wave of 20 points per wavelength by 0.09% per
    operator, 0.3% at 8; now 0.0002% and 0.06% at most: docs/benchmarks.md). The taper g = (1 - d^2/r^2)^2 vanishes
    with its derivative at |d| = r, so the weights stay continuously differentiable in c; a0..a2 solve the 3 x 3
    system of g's moments, a smooth function of c - floor(c). A position on a node keeps its single weight 1 (its
    moments are zero already: a0 = a1 = a2 = 0)."""
    hicks = hicks_weight(dtype)
    radius2 = float(HICKS_RADIUS * HICKS_RADIUS)

    @wp.func
    def taper(d: dtype) -> dtype:
        q = wp.max(dtype(1.0) - d * d / dtype(wp.static(radius2)), dtype(0.0))
        return q * q

    @wp.func
    def axis(d: dtype, c: dtype) -> dtype:
        f = c - wp.floor(c)
        h0 = dtype(0.0)  # h0..h2: moments sum hicks(e) e^p over the nodes, g0..g4 those of the taper
        h1 = dtype(0.0)
        h2 = dtype(0.0)
        g0 = dtype(0.0)
        g1 = dtype(0.0)
        g2 = dtype(0.0)
        g3 = dtype(0.0)
        g4 = dtype(0.0)
        for j in range(wp.static(2 * HICKS_RADIUS)):
            e = dtype(float(j - wp.static(HICKS_RADIUS - 1))) - f
            h = hicks(e)
            g = taper(e)
            h0 = h0 + h
            h1 = h1 + h * e
            h2 = h2 + h * e * e
            g0 = g0 + g
            g1 = g1 + g * e
            g2 = g2 + g * e * e
            g3 = g3 + g * e * e * e
            g4 = g4 + g * e * e * e * e
        # [g0 g1 g2; g1 g2 g3; g2 g3 g4] (a0, a1, a2) = (0, m1, m2) by its adjugate (the matrix is symmetric)
        m1 = -h1 / h0
        m2 = -h2 / h0
        c01 = g2 * g3 - g1 * g4
        c02 = g1 * g3 - g2 * g2
        c11 = g0 * g4 - g2 * g2
        c12 = g1 * g2 - g0 * g3
        c22 = g0 * g2 - g1 * g1
        det = g0 * (g2 * g4 - g3 * g3) + g1 * c01 + g2 * c02
        a0 = (c01 * m1 + c02 * m2) / det
        a1 = (c11 * m1 + c12 * m2) / det
        a2 = (c12 * m1 + c22 * m2) / det
        return hicks(d) / h0 + taper(d) * (a0 + (a1 + a2 * d) * d)

    return axis


def code_key(f) -> str:
    """16 hex digits of the plain values (numbers, strings, None, and tuples, lists, sets and dicts of them) that the
    Python function f, and every Warp func and Python function it reaches through its closure and globals, read from
    their closures and globals: what their wp.static() expressions can be evaluated from.

    Warp 1.19 leaves some of these values out of a module's hash, so a warm kernel cache (WARP_CACHE_PATH) would
    serve a kernel compiled for other values, and a second kernel of the same source in the same process would be
    taken for the first one (issue 29): a wp.static() that reads a loop variable (dtype(wp.static(A[m + 1])) in
    `for m in range(...)`) is evaluated only when the code is generated, and a kernel of module="unique" is hashed
    and named when it is declared, before the Warp funcs it calls are generated, so such values read in a func are
    not hashed; and float constants are hashed as float32, so float64 kernels whose constants differ by less than
    float32's resolution share a hash. Here floats enter by repr (exact), numbers with their type. A value only
    reachable through an attribute of an object (ns.A, numerics.SECOND_DERIVATIVE) is not seen: read it into a
    local or closure name first, as the builders do."""
    memo = {}

    def plain(v):
        # canonical text of plain data, else None (Warp types, structs, arrays and modules: hashed by Warp or unused)
        if v is None or isinstance(v, (bool, str, bytes)):
            return repr(v)
        if isinstance(v, numbers.Number):
            return f"{type(v).__name__}:{v!r}"
        if isinstance(v, (tuple, list)):
            items = [plain(x) for x in v]
            return None if None in items else f"{type(v).__name__}({', '.join(items)})"
        if isinstance(v, (set, frozenset)):
            items = [plain(x) for x in v]
            return None if None in items else f"set({', '.join(sorted(items))})"
        if isinstance(v, dict):
            items = [f"{plain(k)}: {plain(x)}" for k, x in v.items() if plain(k) is not None and plain(x) is not None]
            return None if len(items) < len(v) else f"dict({', '.join(sorted(items))})"
        return None

    def names(code):
        # global names read by code and by the code objects (comprehensions, lambdas) nested in it
        yield from code.co_names
        for c in code.co_consts:
            if isinstance(c, types.CodeType):
                yield from names(c)

    def key(fn) -> str:
        # digest of fn's name, its plain values and, by name, the keys of the functions it reaches (a Merkle tree:
        # which func reads which values); a function met again on its own call path is named only
        if fn in memo:
            return memo[fn] or f"recursive:{fn.__qualname__}"
        memo[fn] = None
        scope = {n: fn.__globals__[n] for n in names(fn.__code__) if n in fn.__globals__}
        for n, cell in zip(fn.__code__.co_freevars, fn.__closure__ or ()):
            try:
                scope[n] = cell.cell_contents
            except ValueError:  # not assigned yet
                scope[n] = "<unassigned>"
        lines = [fn.__qualname__]
        for n, v in sorted(scope.items()):
            if isinstance(v, wp.Function):
                funcs = [g.func for g in (v, *v.user_overloads.values(), *v.user_templates.values())]
                text = f"func({', '.join(key(g) for g in funcs if isinstance(g, types.FunctionType))})"
            elif isinstance(v, types.FunctionType):
                text = f"python({key(v)})"
            else:
                text = plain(v)
            if text is not None:
                lines.append(f"{n}={text}")
        memo[fn] = hashlib.sha256("\n".join(lines).encode()).hexdigest()
        return memo[fn]

    return key(f)[:16]


def unique_kernel(f=None, **options):
    """@unique_kernel or @unique_kernel(**options): wp.kernel(module="unique", **options) whose name (Warp's default,
    the qualified name, and "_" + code_key(f)) carries the values its code is generated from. Warp hashes a kernel's
    name into its module's hash and names the module by both, so kernels generated from other values (a stencil's
    weights, a tile layout, the operator's constants) are other modules, compiled afresh and cached apart. The
    generated arithmetic is unchanged: only the kernel's and module's symbols differ."""

    def wrap(f):
        name = re.sub("[^0-9a-zA-Z_]+", "", f.__qualname__.replace(".", "__"))
        f.code_keyed = True  # read by the module hasher, from the kernel's declaration on
        return wp.kernel(f, name=f"{name}_{code_key(f)}", module="unique", **options)

    return wrap if f is None else wrap(f)


def _hash_modules_of_named_kernels_as_declared():
    """Make the hash of a module of unique_kernel's kernels the same whenever Warp computes it (once per process).

    Warp 1.19 hashes a Warp func with the wp.static() values it evaluated while generating code for it (the deferred
    ones, read through a loop variable), which exist only once some module calling the func has been compiled in this
    process. A module hashed after another one's compile (a cold kernel cache) got another hash than the same module
    hashed in a process that compiles nothing (a warm cache): each run after the first compiled again the modules whose
    funcs another module shares (2-4 s on a GPU; `adseismic bench --fwi`, issue 22). The values are in such a kernel's
    name (code_key), so its module is hashed without them, as before any compile; other modules as Warp does."""
    from warp._src.context import ModuleHasher

    if getattr(ModuleHasher, "code_keyed", False):
        return
    init, hash_adjoint = ModuleHasher.__init__, ModuleHasher.hash_adjoint

    def __init__(self, kernels, options):
        kernels = list(kernels)
        self.code_keyed = bool(kernels) and all(getattr(getattr(k, "func", None), "code_keyed", False) for k in kernels)
        init(self, kernels, options)

    def hash_declared(self, adj):
        if not self.code_keyed or not adj.deferred_static_expressions:
            return hash_adjoint(self, adj)
        kept, adj.deferred_static_expressions = adj.deferred_static_expressions, []
        try:  # under Warp's codegen lock, as every hash and build: no build sees the list emptied
            return hash_adjoint(self, adj)
        finally:
            adj.deferred_static_expressions = kept

    ModuleHasher.__init__, ModuleHasher.hash_adjoint, ModuleHasher.code_keyed = __init__, hash_declared, True


_hash_modules_of_named_kernels_as_declared()


def adjoint_launch(kernel, dim, inputs, adjoints: dict, device):
    """Launch Warp's generated adjoint of `kernel`: adjoints maps input positions to their adjoint arrays;
    the other arrays accumulate into their own .grad, if they have one."""
    adj = [adjoints.get(i, type(a)() if wp.types.is_value(a) and not isinstance(a, (int, float)) else None) for i, a in enumerate(inputs)]
    wp.launch(kernel, dim=dim, inputs=inputs, adj_inputs=adj, adjoint=True, device=device, record_tape=False)


_OPERATORS: "collections.OrderedDict" = None  # host_operator's results, most recent last (OPERATOR_CACHE entries)
OPERATOR_CACHE = 128


def host_operator(kernel, loc: wp.array, args: list, shape: tuple, idx_type, dtype, device):
    """(idx, w): a fixed point operator's nodes (idx_type) and weights (dtype), each `shape`, from kernel(loc, *args,
    idx, w) launched over shape[1:] on the CPU, then copied to `device`. A 3D operator's weights kernel unrolls
    2 HICKS_RADIUS windowed-sinc nodes per axis for each of its point kinds: a GPU compile of it (NVRTC, then ptxas)
    took more than 150 s on an H100 where the CPU's LLVM takes seconds, and it runs once per run. The CPU's work
    (~0.1 s for 500 receivers in 2D) is done once per kernel, locations, arguments and device: the last
    OPERATOR_CACHE results are kept on the device for the next call with the same geometry (an FWI's every
    evaluation, a benchmark's repeats), which gets copies of them."""
    global _OPERATORS
    host_loc = wp.clone(loc, device="cpu", requires_grad=False)
    values = [tuple(a) if hasattr(a, "__len__") else float(a) if isinstance(a, numbers.Real) else a for a in args]
    key = (id(kernel), str(wp.get_device(device)), tuple(shape), idx_type, dtype, repr(values),
           hashlib.sha1(host_loc.numpy().tobytes()).hexdigest())  # fmt: skip
    if _OPERATORS is None:
        _OPERATORS = collections.OrderedDict()
    if key in _OPERATORS:
        _OPERATORS.move_to_end(key)
    else:
        idx = wp.zeros(shape, dtype=idx_type, device="cpu")
        w = wp.zeros(shape, dtype=dtype, device="cpu")
        wp.launch(kernel, dim=shape[1:], inputs=[host_loc, *args, idx, w], device="cpu")
        _OPERATORS[key] = (kernel, (wp.clone(idx, device=device), wp.clone(w, device=device)))  # the kernel kept: its id stays its own
        while len(_OPERATORS) > OPERATOR_CACHE:
            _OPERATORS.popitem(last=False)
    # copies on the device: a caller may refill its arrays (a kept loop copies a later call's operator into its own)
    return tuple(wp.clone(a) for a in _OPERATORS[key][1])


@functools.lru_cache(maxsize=None)
def flat_cpml(dtype):
    """The CPML memory update of the flat staggered kernels, split so that a kernel does all its loads before its
    first store (Warp's arrays may alias, so the compiler holds every load after a store until the store is done):
    psi = cpml_psi(d, j, i, a, b, old, k) = b[i] old[k] + a[i] d at flat strip cell k (profile index i; 0 outside
    the strips, j < 0), the damped derivative is then d + psi, and store_psi(j, new, k, psi) writes psi to new[k]."""
    arr1 = wp.array(dtype=dtype)

    @wp.func
    def cpml_psi(d: dtype, j: int, i: int, a: arr1, b: arr1, old: arr1, k: int) -> dtype:
        if j < 0:
            return dtype(0.0)
        return b[i] * old[k] + a[i] * d

    @wp.func
    def store_psi(j: int, new: arr1, k: int, psi: dtype):
        if j >= 0:
            new[k] = psi

    return cpml_psi, store_psi


@wp.kernel(enable_backward=False)
def lower_bound(keys: wp.array(dtype=wp.int32), first: wp.array(dtype=wp.int32)):
    """first[t]: the number of the sorted keys below t (where key t starts, or would), by binary search."""
    t = wp.tid()
    lo = int(0)
    hi = keys.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if keys[mid] < t:
            lo = mid + 1
        else:
            hi = mid
    first[t] = lo


def check_flat_cells(cells: int, what: str) -> None:
    """Refuse (ValueError) an array of `cells` cells past the flat field kernels' int32 indices (2^31)."""
    if cells >= 2**31:
        raise ValueError(f"{what} needs an array of {cells} cells, above the 2^31 - 1 of the kernels' int32 flat indices; use fewer "
                         f"shots per call or a smaller grid")


def block_rows(n: int, i: int, parts: int):
    """Rows [r0, r1) of block i of n rows split into `parts` blocks."""
    return n * i // parts, n * (i + 1) // parts


class Kernels:
    """Namespace of the compiled kernels of one configuration (see build)."""

    def __init__(self, **kw):
        self.__dict__.update(kw)


def operator_shape(op) -> tuple:
    """What a captured loop bakes in of a source/receiver operator (Acoustic.operator): its points' shape (S, n,
    points) or, for locations, theirs."""
    return tuple((op[1] if isinstance(op, tuple) else op).shape) + (isinstance(op, tuple),)


def as_vectors(a: wp.array, V: int) -> wp.array:
    """a's memory as a flat array of vector(V) (the core tiles' loads and stores; a.size a multiple of V)."""
    flat = a.flatten()
    return (flat if V == 1 else flat.reshape((a.size // V, V))).view(wp.types.vector(length=V, dtype=a.dtype))


@functools.lru_cache(maxsize=None)
def flat_access(dtype):
    """(load3(a, i), load4(a, i), store4(a, i, v), add4(a, i, v)): element i of a contiguous 3D or 4D array a of dtype in its flat
    order, for kernels that address cells by a flat offset and its neighbours by adding strides. Indexing (s, z, y, x)
    costs four multiply-adds and four negative-index checks a load; a GPU step that reads ~30 values a cell is then
    bound by that integer arithmetic (docs/benchmarks.md, "Flat offsets in the frame"). Not differentiable: for the
    GPU steps, not the kernels Warp's tape records."""
    arr3, arr4 = wp.array3d(dtype=dtype), wp.array4d(dtype=dtype)

    @wp.func_native("return a.data[i];\n")
    def load3(a: arr3, i: int) -> dtype: ...

    @wp.func_native("return a.data[i];\n")
    def load4(a: arr4, i: int) -> dtype: ...

    @wp.func_native("a.data[i] = v;\n")
    def store4(a: arr4, i: int, v: dtype): ...

    @wp.func_native("wp::atomic_add(a.data + i, v);\n")
    def add4(a: arr4, i: int, v: dtype): ...

    return load3, load4, store4, add4


@functools.lru_cache(maxsize=None)
def vector_access(V: int, dtype):
    """(load(f, i), store(f, i, v)) of element i of a contiguous array f of vector(V, dtype), as one access of
    V * itemsize bytes (two of 16 for 32) on a GPU: Warp indexes a vector array component by component, and the GPU
    then moves 4 bytes per instruction with a stride of the vector's size between threads. The CPU indexes as Warp does."""
    vec = wp.types.vector(length=V, dtype=dtype)
    arrv = wp.array(dtype=vec)
    size = V * wp.types.type_size_in_bytes(dtype)
    word, n = {8: ("uint2", 1), 16: ("uint4", 1), 32: ("uint4", 2)}.get(size, (None, 0))
    load, store = "return f.data[i];\n", "f.data[i] = v;\n"
    if word is not None:  # the #if lines need their own lines, and the last a newline
        cuda = f"#if defined(__CUDA_ARCH__)\n{word} u[{n}];\n"
        load = (f"{cuda}const {word}* p = reinterpret_cast<const {word}*>(f.data + i);\nfor (int k = 0; k < {n}; ++k) u[k] = p[k];\n"
                f"wp::vec_t<{V},wp::{dtype.__name__}> r;\nmemcpy(&r, u, {size});\nreturn r;\n#else\n{load}#endif\n")
        store = (f"{cuda}memcpy(u, &v, {size});\n{word}* p = reinterpret_cast<{word}*>(f.data + i);\n"
                 f"for (int k = 0; k < {n}; ++k) p[k] = u[k];\n#else\n{store}#endif\n")

    @wp.func_native(load)
    def load_vector(f: arrv, i: int) -> vec: ...

    @wp.func_native(store)
    def store_vector(f: arrv, i: int, v: vec): ...

    return load_vector, store_vector


@functools.lru_cache(maxsize=None)
def frame_map(R: int):
    """frame_cell(f, lz, lx, box) -> (z, x): the f-th interior cell of a 2D padded grid (lz, lx) with a halo of R cells
    outside the box of rows [box[0], box[1]) x columns [box[2], box[3]) (padded indices): first the full rows above and
    below the box, then the left and right parts of its rows (a core-and-frame launch's frame threads)."""

    @wp.func
    def frame_cell(f: int, lz: int, lx: int, box: wp.vec4i) -> wp.vec2i:
        nx = lx - wp.static(2 * R)
        above = (box[0] - wp.static(R)) * nx
        below = (lz - wp.static(R) - box[1]) * nx
        if f < above:
            return wp.vec2i(wp.static(R) + f // nx, wp.static(R) + f % nx)
        if f < above + below:
            return wp.vec2i(box[1] + (f - above) // nx, wp.static(R) + (f - above) % nx)
        g = f - above - below
        sides = box[2] - wp.static(R) + lx - wp.static(R) - box[3]
        x = wp.static(R) + g % sides
        if x >= box[2]:
            x = x - box[2] + box[3]
        return wp.vec2i(box[0] + g // sides, x)

    return frame_cell


def aligned(z0: int, z1: int, x0: int, x1: int, V: int) -> wp.vec4i:
    """The box of rows [z0, z1) and of the columns of [x0, x1) from and to a multiple of V."""
    return wp.vec4i(z0, z1, -(-x0 // V) * V, x1 // V * V)


@dataclass(frozen=True)
class Description:
    """What the solver and the planner need to know of a physics, without its kernels.

    fields: the wavefield's components and their units; parameters: the model's arrays (axis order
    (z, [y,] x)) and their units; ndims: the supported dimensions; orders: spatial orders; stencil: the
    derivative weights by order; injection: how sources and receivers meet the grid; courant_speed:
    the parameter whose maximum sets the time step; cfl_limit(order, ndim): largest stable
    courant_speed dt / dx; dispersion_error(order, ndim, ppw, courant): the scheme's exact relative
    phase and group velocity errors ({"phase", "group"}: worst over directions) at ppw points per
    wavelength.
    """

    name: str
    fields: dict
    parameters: dict
    ndims: tuple
    orders: tuple
    stencil: dict
    injection: str
    courant_speed: str
    cfl_limit: Callable[[int, int], float]
    dispersion_error: Callable[..., dict]
