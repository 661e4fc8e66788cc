"""Import an EDS with python-canopen and print selected values (crates/canopen/tests/python_canopen.rs).

usage: read_eds.py FILE NODE INDEX:SUB...
Prints one line per object: INDEX:SUB NAME DEFAULT.
"""

import sys

import canopen


def main():
    path, node_id = sys.argv[1], int(sys.argv[2])
    od = canopen.import_od(path, node_id)
    for spec in sys.argv[3:]:
        index, sub = (int(x, 16) for x in spec.split(":"))
        obj = od[index]
        var = obj[sub] if isinstance(obj, (canopen.objectdictionary.ODRecord, canopen.objectdictionary.ODArray)) else obj
        print(f"{spec} {var.name} {var.default}")


if __name__ == "__main__":
    main()
