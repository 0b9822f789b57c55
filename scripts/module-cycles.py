#!/usr/bin/env python3
"""Refuses import cycles between the top-level modules of each crate (ARCHITECTURE.md: modules
depend one way). A module is a file or folder under src/; an edge is a `crate::name` path in its
code outside `#[cfg(test)]`. Usage: module-cycles.py SRC_DIR..."""
import os
import re
import sys
from collections import defaultdict


def module_edges(src):
    edges = defaultdict(set)
    for root, _, files in os.walk(src):
        for name in files:
            if not name.endswith(".rs"):
                continue
            path = os.path.join(root, name)
            parts = os.path.relpath(path, src)[:-3].split(os.sep)
            if parts in (["lib"], ["main"]) or parts[0] == "bin":
                continue
            text = open(path, encoding="utf-8").read()
            tests = text.find("#[cfg(test)]")
            if tests >= 0:
                text = text[:tests]
            text = re.sub(r"//.*", "", text)
            for used in re.findall(r"crate::([a-z_0-9]+)", text):
                if used != parts[0]:
                    edges[parts[0]].add(used)
    return edges


def cycles(edges):
    found, state, stack = [], {}, []

    def visit(module):
        state[module] = "open"
        stack.append(module)
        for used in sorted(edges.get(module, ())):
            if state.get(used) == "open":
                found.append(stack[stack.index(used):] + [used])
            elif used not in state:
                visit(used)
        stack.pop()
        state[module] = "done"

    for module in sorted(edges):
        if module not in state:
            visit(module)
    return found


failed = False
for src in sys.argv[1:]:
    for cycle in cycles(module_edges(src)):
        print(f"module-cycles: {src}: {' -> '.join(cycle)}", file=sys.stderr)
        failed = True
sys.exit(1 if failed else 0)
