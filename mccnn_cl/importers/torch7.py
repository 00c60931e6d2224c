"""Torch7 ``.t7`` files (ASCII serialisation) read without Lua or torch.

:func:`read_t7` walks Torch7's ``File:writeObject`` tree: a type tag (nil,
number, string, table, torch object, boolean, function), then for tables,
torch objects and functions an object index, with repeated objects written
as a back-reference to that index.  Torch objects carry ``"V <version>"`` and
a class name; tensors are ``nDimension``, sizes, strides, a 1-based offset
and their storage (another torch object), storages a count and that many
numbers (raw bytes for Byte/Char storages).  Every other class is a table of
fields.  Functions (the modules' LuaJIT bytecode) are kept as bytes and
never run.  In ASCII mode numbers are text separated by whitespace; strings
are a length and raw bytes, each item followed by one newline.

:func:`network` then checks the tree: the authors' MC-CNN-fst test network
(``main.lua`` saves ``{net_te, opt}``), an ``nn.Sequential`` of
convolutions with ReLU between them, ``nn.Normalize2`` (x / sqrt(|x|^2 +
1e-5) over the feature maps) and ``nn.StereoJoin1`` / ``nn.StereoJoin``.
Anything else is a :class:`~mccnn_cl.errors.WeightsError` that says what was
expected and what was found.
"""

from __future__ import annotations

import numpy as np

from ..errors import WeightsError

NIL, NUMBER, STRING, TABLE, TORCH, BOOLEAN, FUNCTION, LEGACY_RECUR_FUNCTION, RECUR_FUNCTION = range(9)
MAX_DEPTH = 200
_WHITESPACE = b" \t\r\n\v\f"
_STORAGE_DTYPES = {"Byte": np.uint8, "Char": np.int8, "Short": np.int16, "Int": np.int32,
                   "Long": np.int64, "Float": np.float32, "Double": np.float64,
                   "Cuda": np.float32, "CudaDouble": np.float64, "CudaLong": np.int64,
                   "CudaInt": np.int32, "CudaByte": np.uint8, "CudaChar": np.int8,
                   "CudaShort": np.int16, "CudaHalf": np.float16}


class T7Table(dict):
    """A Lua table (keys: float numbers, strings, booleans or other objects)."""

    __hash__ = object.__hash__  # tables are compared by identity, as in Lua

    def __eq__(self, other):
        return self is other


class T7Object:
    """A torch object of a Lua class (``nn.*``, ``cudnn.*``): its fields."""

    def __init__(self, class_name, version):
        self.class_name, self.version, self.fields = class_name, version, T7Table()

    def __repr__(self):
        return f"<{self.class_name}>"


class T7Storage:
    def __init__(self, class_name, data):
        self.class_name, self.data = class_name, data

    def __repr__(self):
        return f"<{self.class_name} of {self.data.size}>"


class T7Tensor:
    def __init__(self, class_name, size, stride, offset, storage):
        self.class_name, self.size, self.stride = class_name, tuple(size), tuple(stride)
        self.offset, self.storage = offset, storage  # offset 0-based

    def __repr__(self):
        return f"<{self.class_name} {'x'.join(map(str, self.size)) or 'empty'}>"

    def numpy(self, what="tensor") -> np.ndarray:
        """The tensor's elements as a new C-contiguous array (bounds checked)."""
        if not self.size or 0 in self.size:
            return np.zeros(self.size, np.float32)
        if self.storage is None:
            raise WeightsError(f"{what}: {self.class_name} of size {self.size} has no storage")
        data = self.storage.data
        if min(self.stride) < 0 or self.offset < 0:
            raise WeightsError(f"{what}: negative stride or offset {self.stride}/{self.offset}")
        last = self.offset + sum((n - 1) * s for n, s in zip(self.size, self.stride))
        if last >= data.size:
            raise WeightsError(f"{what}: tensor of size {self.size} reaches element {last + 1} "
                               f"of a storage of {data.size}")
        view = np.lib.stride_tricks.as_strided(
            data[self.offset:], shape=self.size, strides=[s * data.itemsize for s in self.stride],
            writeable=False)
        return np.array(view, order="C")


class T7Function:
    """A serialised Lua function: its bytecode as bytes (never loaded) and upvalues."""

    def __init__(self, bytecode):
        self.bytecode, self.upvalues = bytecode, None

    def __repr__(self):
        return f"<function, {len(self.bytecode)} bytes of bytecode>"


class _Reader:
    def __init__(self, data: bytes, name: str):
        self.buf, self.pos, self.name = data, 0, name
        self.objects = {}

    # -- primitives ------------------------------------------------------
    def fail(self, what):
        raise WeightsError(f"{self.name}: not a Torch7 ASCII file of a network: {what} "
                           f"(at byte {self.pos} of {len(self.buf)})")

    def token(self, what) -> bytes:
        buf, n, i = self.buf, len(self.buf), self.pos
        while i < n and buf[i] in _WHITESPACE:
            i += 1
        j = i
        while j < n and buf[j] not in _WHITESPACE:
            j += 1
        if i == j:
            self.pos = i
            self.fail(f"file ends where {what} was expected")
        tok = buf[i:j]
        self.pos = j + 1 if j < n and buf[j] == 0x0A else j  # one newline follows each item
        return tok

    def int(self, what, lo=None, hi=None) -> int:
        tok = self.token(what)
        try:
            value = int(tok)
        except ValueError:
            self.fail(f"expected an integer for {what}, found {tok[:20]!r}")
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            self.fail(f"{what} = {value} is out of range [{lo}, {hi}]")
        return value

    def number(self, what) -> float:
        tok = self.token(what)
        try:
            return float(tok)
        except ValueError:
            self.fail(f"expected a number for {what}, found {tok[:20]!r}")

    def raw(self, n, what) -> bytes:
        if self.pos + n > len(self.buf):
            self.fail(f"{what} of {n} bytes runs past the end of the file")
        data = self.buf[self.pos:self.pos + n]
        self.pos += n
        if self.pos < len(self.buf) and self.buf[self.pos] == 0x0A:
            self.pos += 1
        return data

    def string(self, what) -> bytes:
        return self.raw(self.int(f"length of {what}", 0, len(self.buf) - self.pos), what)

    def numbers(self, count, dtype, what) -> np.ndarray:
        """``count`` numbers of one line (ASCII arrays are written space-separated, then a newline)."""
        if count == 0:
            return np.zeros(0, dtype)
        end = self.buf.find(b"\n", self.pos)
        end = len(self.buf) if end < 0 else end
        toks = self.buf[self.pos:end].split()
        if len(toks) != count:
            self.fail(f"{what}: expected {count} numbers, found {len(toks)}")
        try:
            if np.issubdtype(dtype, np.integer):
                values = np.array([int(t) for t in toks], dtype=np.int64).astype(dtype)
            else:
                values = np.array([float(t) for t in toks], dtype=np.float64).astype(dtype)
        except ValueError:
            self.fail(f"{what}: a value is not a number")
        self.pos = min(end + 1, len(self.buf))
        return values

    # -- objects -----------------------------------------------------------
    def object(self, depth=0):
        if depth > MAX_DEPTH:
            self.fail(f"objects nested deeper than {MAX_DEPTH}")
        tag = self.int("a type tag", 0, 8)
        if tag == NIL:
            return None
        if tag == NUMBER:
            return self.number("a number")
        if tag == BOOLEAN:
            return self.int("a boolean", 0, 1) == 1
        if tag == STRING:
            return self.string("a string").decode("latin-1")
        if tag == FUNCTION:  # old non-recursive form: no index
            fn = T7Function(self.string("function bytecode"))
            fn.upvalues = self.object(depth + 1)
            return fn
        index = self.int("an object index", 1)
        if index in self.objects:
            return self.objects[index]
        if index != len(self.objects) + 1:
            self.fail(f"object index {index} refers to no object read so far ({len(self.objects)} read)")
        if tag in (RECUR_FUNCTION, LEGACY_RECUR_FUNCTION):
            fn = self.objects[index] = T7Function(self.string("function bytecode"))
            fn.upvalues = self.object(depth + 1)
            return fn
        if tag == TABLE:
            table = self.objects[index] = T7Table()
            for _ in range(self.int("a table size", 0, len(self.buf) - self.pos)):
                key = self.object(depth + 1)
                if key is None:
                    self.fail("a table key is nil")
                table[key] = self.object(depth + 1)
            return table
        return self.torch_object(index, depth)

    def torch_object(self, index, depth):
        head = self.string("a torch class version").decode("latin-1")
        if head.startswith("V "):
            try:
                version = int(head[2:])
            except ValueError:
                self.fail(f"bad class version {head!r}")
            cls = self.string("a torch class name").decode("latin-1")
        else:
            version, cls = 0, head
        if not cls.replace(".", "").replace("_", "").isalnum():
            self.fail(f"bad torch class name {cls[:40]!r}")
        pkg, _, base = cls.partition(".")
        if pkg == "torch" and base.endswith("Storage") and base[:-7] in _STORAGE_DTYPES:
            dtype = _STORAGE_DTYPES[base[:-7]]
            count = self.int(f"the size of a {cls}", 0, len(self.buf) - self.pos)
            if dtype in (np.uint8, np.int8):
                data = np.frombuffer(self.raw(count, cls), dtype).copy()
            else:
                data = self.numbers(count, dtype, cls)
            obj = self.objects[index] = T7Storage(cls, data)
            return obj
        if pkg == "torch" and base.endswith("Tensor") and base[:-6] in _STORAGE_DTYPES:
            ndim = self.int(f"the dimension of a {cls}", 0, 32)
            size = self.numbers(ndim, np.int64, f"{cls} sizes")
            stride = self.numbers(ndim, np.int64, f"{cls} strides")
            offset = self.int(f"the offset of a {cls}", 1) - 1
            tensor = self.objects[index] = T7Tensor(cls, size.tolist(), stride.tolist(), offset, None)
            storage = self.object(depth + 1)
            if storage is not None and not isinstance(storage, T7Storage):
                self.fail(f"a {cls}'s storage is a {type(storage).__name__}")
            if any(n < 0 for n in tensor.size):
                self.fail(f"a {cls} has negative sizes {tensor.size}")
            tensor.storage = storage
            return tensor
        obj = self.objects[index] = T7Object(cls, version)
        fields = self.object(depth + 1)
        if not isinstance(fields, T7Table):
            self.fail(f"{cls}'s fields are not a table")
        obj.fields = fields
        return obj


def read_t7(path):
    """The object tree of a Torch7 ASCII file (see the module docstring)."""
    name = str(path)
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as exc:
        raise WeightsError(f"{name}: cannot read ({exc.strerror or exc})") from exc
    if not data.strip():
        raise WeightsError(f"{name}: empty file; expected a Torch7 ASCII network")
    r = _Reader(data, name)
    root = r.object()
    rest = data[r.pos:].strip()
    if rest:
        r.fail(f"{len(rest)} bytes follow the first object")
    return root


# -- the network ----------------------------------------------------------------

CONV_TYPES = ("cudnn.SpatialConvolution", "nn.SpatialConvolution", "nn.SpatialConvolutionMM")
RELU_TYPES = ("cudnn.ReLU", "nn.ReLU")
NORMALIZE_TYPES = ("nn.Normalize2",)
JOIN_TYPES = ("nn.StereoJoin1", "nn.StereoJoin")
EXPECTED = ("an nn.Sequential of cudnn/nn.SpatialConvolution with cudnn/nn.ReLU between them, "
            "then nn.Normalize2 and nn.StereoJoin1 (MC-CNN-fst)")


def _kind(obj) -> str:
    if isinstance(obj, T7Object):
        return obj.class_name
    if isinstance(obj, T7Table):
        return f"a table of {len(obj)} entries"
    if isinstance(obj, (T7Tensor, T7Storage)):
        return obj.class_name
    if isinstance(obj, T7Function):
        return "a Lua function"
    return f"a {type(obj).__name__}" if obj is not None else "nil"


def _sequence(table, what):
    """Lua array part 1..n of a table, in order."""
    n = len(table)
    items = [table.get(float(i)) for i in range(1, n + 1)]
    if any(v is None for v in items):
        raise WeightsError(f"{what}: modules are not a list 1..{n}")
    return items


def _number(module, key, what):
    v = module.fields.get(key)
    if not isinstance(v, float) or v != int(v):
        raise WeightsError(f"{what}: field {key} is {_kind(v)}, expected an integer")
    return int(v)


def network(root, name):
    """Check a read ``.t7`` tree; returns (conv layers [(W, b)], facts dict)."""
    net = root
    if isinstance(root, T7Table) and 1.0 in root:  # main.lua saves {net_te, opt}
        net = root[1.0]
    if not (isinstance(net, T7Object) and net.class_name == "nn.Sequential"):
        held = (f"a table whose first entry is {_kind(net)}" if net is not root else _kind(net))
        raise WeightsError(f"{name}: expected {EXPECTED}; the file holds {held}")
    modules = net.fields.get("modules")
    if not isinstance(modules, T7Table):
        raise WeightsError(f"{name}: nn.Sequential has no module list (expected {EXPECTED})")
    mods = _sequence(modules, name)
    kinds = [_kind(m) for m in mods]
    found = ", ".join(k.split(".")[-1] for k in kinds) or "no modules"
    conv, pads, relu_after = [], [], []
    i = 0
    while i < len(mods) and kinds[i] in CONV_TYPES:
        conv.append(_conv(mods[i], f"{name}: module {i + 1} ({kinds[i]})"))
        pads.append((_number(mods[i], "padH", name) if "padH" in mods[i].fields else 0,
                     _number(mods[i], "padW", name) if "padW" in mods[i].fields else 0))
        i += 1
        relu_after.append(i < len(mods) and kinds[i] in RELU_TYPES)
        if relu_after[-1]:
            i += 1
    tail = kinds[i:]
    ok = (conv and all(relu_after[:-1]) and not relu_after[-1]
          and len(tail) in (1, 2) and tail[0] in NORMALIZE_TYPES
          and (len(tail) == 1 or tail[1] in JOIN_TYPES))
    if not ok:
        raise WeightsError(f"{name}: expected {EXPECTED}; found {found}")
    if conv[0][0].shape[1] != 1:
        raise WeightsError(f"{name}: the first convolution takes {conv[0][0].shape[1]} input channels; mccnn_cl "
                           f"runs networks of 1 gray channel (main.lua -color gray), not colour ones")
    for j in range(1, len(conv)):
        if conv[j][0].shape[1] != conv[j - 1][0].shape[0]:
            raise WeightsError(f"{name}: conv layer {j + 1} takes {conv[j][0].shape[1]} maps, "
                               f"layer {j} gives {conv[j - 1][0].shape[0]} (expected chained shapes)")
    opt = root.get(2.0) if isinstance(root, T7Table) else None
    facts = {"modules": [k for k in kinds], "padding": pads,
             "options": {k: v for k, v in opt.items() if isinstance(k, str) and isinstance(v, (float, str, bool))}
             if isinstance(opt, T7Table) else {}}
    return conv, facts


def _conv(module, what):
    f = module.fields
    w, b = f.get("weight"), f.get("bias")
    if not isinstance(w, T7Tensor) or not isinstance(b, T7Tensor):
        raise WeightsError(f"{what}: weight/bias are {_kind(w)}/{_kind(b)}, expected tensors")
    nin, nout = _number(module, "nInputPlane", what), _number(module, "nOutputPlane", what)
    kh, kw = _number(module, "kH", what), _number(module, "kW", what)
    dh, dw = (_number(module, k, what) if k in f else 1 for k in ("dH", "dW"))
    if kh != kw or (dh, dw) != (1, 1):
        raise WeightsError(f"{what}: expected square kernels with stride 1, found {kh}x{kw} stride {dh}x{dw}")
    W, B = w.numpy(f"{what} weight"), b.numpy(f"{what} bias")
    if W.size != nout * nin * kh * kw or B.shape != (nout,):
        raise WeightsError(f"{what}: weight {W.shape} / bias {B.shape} disagree with "
                           f"{nin} -> {nout} maps of {kh}x{kw}")
    W = W.reshape(nout, nin, kh, kw).astype(np.float32)
    return W, B.astype(np.float32)
