"""Generate the C frame codec of a DBC: what ``cantools generate_c_source DBC -o OUTDIR`` does
(same cantools generator, same files: <dbc name>.h and <dbc name>.c), without loading the
cantools command line, whose plot subcommand imports matplotlib (minutes on a slow board or an
emulated VM).

    python gen_codec.py build/canbrake.dbc build
"""
import os
import sys

from cantools.database import load_file
from cantools.database.can.c_source import camel_to_snake_case, generate


def main(dbc: str, out_dir: str) -> None:
    name = camel_to_snake_case(os.path.splitext(os.path.basename(dbc))[0])
    header, source, _fuzzer, _fuzzer_mk = generate(load_file(dbc), name, f"{name}.h", f"{name}.c",
                                                   f"{name}_fuzzer.c")
    os.makedirs(out_dir, exist_ok=True)
    for file_name, text in ((f"{name}.h", header), (f"{name}.c", source)):
        with open(os.path.join(out_dir, file_name), "w") as f:
            f.write(text)
    print(f"generated {os.path.join(out_dir, name)}.h and .c from {dbc}")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python gen_codec.py DBC OUTDIR")
    main(sys.argv[1], sys.argv[2])
