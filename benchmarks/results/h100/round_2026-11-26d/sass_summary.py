"""Summaries of ncu's SASS source pages (call 12): executed warp-instructions, the highest register, the opcode mix,
and the kernel in windows of 250 instructions (highest register, executed instructions, main opcodes, whether it
holds warp shuffles or MUFU), then the instructions that touch the highest registers.

    python benchmarks/results/h100/round_2026-11-26d/sass_summary.py FILE.csv.gz [FILE.csv.gz ...]
"""
import collections
import csv
import gzip
import io
import re
import sys


def load(path):
    with gzip.open(path, "rt") if path.endswith(".gz") else open(path) as f:
        rows = list(csv.reader(io.StringIO(f.read())))
    start = next(i for i, r in enumerate(rows) if r and r[0] == "Address")
    return [(r[1].strip(), int(r[5] or 0)) for r in rows[start + 1:] if len(r) > 5]


def opcode(sass):
    return (sass.split()[1] if sass.startswith("@") else sass.split()[0]).split(".")[0]


def top_register(sass):
    return max([int(x) for x in re.findall(r"\bR(\d+)\b", sass)] or [-1])


for path in sys.argv[1:]:
    ins = load(path)
    total = sum(e for _, e in ins)
    regs = [top_register(s) for s, _ in ins]
    mix = collections.Counter()
    for s, e in ins:
        mix[opcode(s)] += e
    print(f"{path}: {len(ins)} instructions, {total} executed warp-instructions, highest register R{max(regs)}")
    print("  executed mix:", ", ".join(f"{k} {v / total:.1%}" for k, v in mix.most_common(10)))
    for a in range(0, len(ins), 250):
        seg = ins[a:a + 250]
        ops = collections.Counter(opcode(s) for s, _ in seg)
        print(f"  [{a:5d}, {a + len(seg):5d})  highest R{max(regs[a:a + 250]):3d}  executed {sum(e for _, e in seg) / 1e6:7.1f} M"
              f"  {' '.join(k for k, _ in ops.most_common(5)):40s} shuffles {'SHFL' in ops or 'REDUX' in ops!s:5s}"
              f" MUFU {ops.get('MUFU', 0)}")
    high = max(regs) - 13
    print(f"  instructions touching R{high} or above:")
    for i, (s, e) in enumerate(ins):
        if regs[i] >= high:
            print(f"    {i:5d} {e:10d}  {s}")
