"""The file formats of the authors' C tools (mregn / rnn-learn, Namikawa & Tani 2010), so that
their programs train on moex's data and moex scores their networks.

Target files (read by `mre-learn`, `rnn-learn`): one step per line, columns separated by tabs,
a blank line between series, `#` comments.
"""

from pathlib import Path

import numpy as np


def write_targets(path, series: np.ndarray, header: str = "") -> Path:
    """Write (S, T, D) series as one target file of the C tools (a blank line between series),
    with `%.17g` so that the file reads back to the same float64 values."""
    path = Path(path)
    lines = [f"# {line}" for line in header.splitlines()]
    for s, one in enumerate(series):
        if s:
            lines.append("")
        lines += ["\t".join(f"{v:.17g}" for v in row) for row in one]
    path.write_text("\n".join(lines) + "\n")
    return path


def read_targets(path) -> list[np.ndarray]:
    """The series of a C target file, each (T_s, D): blank or comment-only lines split series."""
    series, rows = [], []
    for line in Path(path).read_text().splitlines():
        text = line.split("#", 1)[0].strip()
        if not text:
            if rows:
                series.append(np.array(rows, dtype=np.float64))
                rows = []
            continue
        rows.append([float(v) for v in text.replace(",", " ").split()])
    if rows:
        series.append(np.array(rows, dtype=np.float64))
    return series


# ---- binary save files (`rnn.dat`, `mre.dat`, `gn.dat`): C structs written field by field with
# fwrite on a 64-bit Linux build: int and enum 4 bytes, long 8, double 8, little-endian.
# Each layout is a list of (name, dtype, shape) where shape may name earlier sizes; one list
# drives both reading and writing, so that a file read and written back is the same file.

def _rnn_parameters(p):
    n_in, M, n_out = p["in_state_size"], p["c_state_size"], p["out_state_size"]
    rows = [("weight_ci", "f8", (n_in,)), ("weight_cc", "f8", (M,)),
            ("delta_weight_ci", "f8", (n_in,)), ("delta_weight_cc", "f8", (M,)),
            ("prior_weight_ci", "f8", (n_in,)), ("prior_weight_cc", "f8", (M,))]
    out_rows = [("weight_oc", "f8", (M,)), ("delta_weight_oc", "f8", (M,)),
                ("prior_weight_oc", "f8", (M,))]
    return ([("const_init_c", "i4", (M,)), ("softmax_group_id", "i4", (n_out,))]
            + [("ci_block", rows, M), ("oc_block", out_rows, n_out)]
            + [(name, "f8", (size,)) for name, size in (
                ("threshold_c", M), ("threshold_o", n_out), ("tau", M), ("eta", M),
                ("delta_threshold_c", M), ("delta_threshold_o", n_out), ("delta_tau", M),
                ("prior_threshold_c", M), ("prior_threshold_o", n_out), ("prior_tau", M))]
            + [("connection_ci", "i4", (M, n_in + 1, 2)), ("connection_cc", "i4", (M, M + 1, 2)),
               ("connection_oc", "i4", (n_out, M + 1, 2))])


_RNN_HEADER = [(name, "i4", ()) for name in (
    "in_state_size", "c_state_size", "out_state_size", "output_type", "fixed_weight",
    "fixed_threshold", "fixed_tau", "fixed_init_c_state", "fixed_sigma", "softmax_group_num")] + [
    (name, "f8", ()) for name in ("sigma", "delta_sigma", "prior_strength", "prior_sigma")]


class _Stream:
    """A cursor over the bytes of a save file (reading) or a list of chunks (writing)."""

    def __init__(self, data: bytes | None = None):
        self.data, self.pos, self.chunks = data, 0, []

    def read(self, dtype: str, shape) -> np.ndarray:
        count = int(np.prod(shape, dtype=np.int64)) if shape else 1
        size = np.dtype(dtype).itemsize * count
        if self.data is None or self.pos + size > len(self.data):
            raise ValueError(f"the file ends early (at byte {self.pos}, {size} more needed)")
        value = np.frombuffer(self.data, "<" + dtype, count, self.pos).reshape(shape)
        self.pos += size
        return value.copy() if shape else value.item()

    def write(self, dtype: str, shape, value) -> None:
        array = np.asarray(value, dtype="<" + dtype)
        if array.shape != tuple(shape):
            raise ValueError(f"a field has shape {array.shape}, its layout says {tuple(shape)}")
        self.chunks.append(array.tobytes())


def _fields(stream: _Stream, layout, record: dict | None) -> dict:
    """Read (record None) or write (record given) the fields of a layout in order."""
    out = {} if record is None else record
    for name, kind, shape in layout:
        if isinstance(kind, list):  # a block of per-row fields interleaved row by row
            if record is None:
                rows = [{n: stream.read(d, s) for n, d, s in kind} for _ in range(shape)]
                for n, d, s in kind:
                    out[n] = np.array([r[n] for r in rows], dtype=d).reshape((shape,) + s)
            else:
                for i in range(shape):
                    for n, d, s in kind:
                        stream.write(d, s, record[n][i])
        elif record is None:
            out[name] = stream.read(kind, shape)
        else:
            stream.write(kind, shape, record[name])
    return out


def _rnn(stream: _Stream, record: dict | None = None) -> dict:
    """One `recurrent_neural_network`: parameters, then each series' state (u_0, c_0, data)."""
    head = _fields(stream, _RNN_HEADER, None if record is None else record)
    body = _fields(stream, _rnn_parameters(head), None if record is None else record)
    net = {**head, **body}
    n_in, M, n_out = head["in_state_size"], head["c_state_size"], head["out_state_size"]
    if record is None:
        net["series"] = []
        for _ in range(stream.read("i4", ())):
            length = stream.read("i4", ())
            state = _fields(stream, [("init_c_inter_state", "f8", (M,)),
                                     ("init_c_state", "f8", (M,)),
                                     ("delta_init_c_inter_state", "f8", (M,))], None)
            pairs = stream.read("f8", (length, n_in + n_out))
            net["series"].append({**state, "in_state": pairs[:, :n_in],
                                  "teach_state": pairs[:, n_in:]})
    else:
        stream.write("i4", (), len(record["series"]))
        for s in record["series"]:
            stream.write("i4", (), len(s["in_state"]))
            for name in ("init_c_inter_state", "init_c_state", "delta_init_c_inter_state"):
                stream.write("f8", (M,), s[name])
            stream.write("f8", (len(s["in_state"]), n_in + n_out),
                         np.concatenate([s["in_state"], s["teach_state"]], axis=1))
    return net


def _mre(stream: _Stream, record: dict | None = None) -> dict:
    """A `mixture_of_rnn_experts`: sizes, γ, each expert, then each series' gates and β."""
    head = _fields(stream, [(n, "i4", ()) for n in (
        "expert_num", "series_num", "in_state_size", "out_state_size", "fixed_gate",
        "gate_prior_distribution")], record)
    K, S = head["expert_num"], head["series_num"]
    mre = {**head, **_fields(stream, [("gamma", "f8", (K,))], record)}
    if record is None:
        mre["experts"] = [_rnn(stream) for _ in range(K)]
        mre["series"] = []
        for _ in range(S):
            length = stream.read("i4", ())
            blocks = stream.read("f8", (K, 3, length))  # per expert: gate, beta, delta_beta
            mre["series"].append({"gate": blocks[:, 0], "beta": blocks[:, 1],
                                  "delta_beta": blocks[:, 2]})
    else:
        for expert in record["experts"]:
            _rnn(stream, expert)
        for s in record["series"]:
            length = s["gate"].shape[1]
            stream.write("i4", (), length)
            stream.write("f8", (K, 3, length), np.stack([s["gate"], s["beta"], s["delta_beta"]], 1))
    return mre


KINDS = {"rnn.dat": _rnn, "mre.dat": _mre, "gn.dat": _rnn}  # the learners' default file names


def read_save(path, kind: str | None = None) -> dict:
    """A learner's save file: {"delay", "net" (the network), "adapt_lr", "epoch"}. `kind` is
    rnn.dat (rnn-learn), mre.dat (mre-learn) or gn.dat (gn-learn); by default the file's name."""
    path = Path(path)
    codec = KINDS.get(kind or path.name)
    if codec is None:
        raise ValueError(f"{path}: name the kind of file (one of {', '.join(KINDS)})")
    stream = _Stream(path.read_bytes())
    record = {"delay": stream.read("i4", ()), "net": codec(stream),
              "adapt_lr": stream.read("f8", ()), "epoch": stream.read("i8", ())}
    if stream.pos != len(stream.data):
        raise ValueError(f"{path}: {len(stream.data) - stream.pos} bytes left after the "
                         f"{kind or path.name} layout; it is not a file of that kind")
    return record


def write_save(path, record: dict, kind: str) -> Path:
    """Write a record of `read_save` back in the learners' format (the inverse of read_save)."""
    stream = _Stream()
    stream.write("i4", (), record["delay"])
    KINDS[kind](stream, record["net"])
    stream.write("f8", (), record["adapt_lr"])
    stream.write("i8", (), record["epoch"])
    Path(path).write_bytes(b"".join(stream.chunks))
    return Path(path)
