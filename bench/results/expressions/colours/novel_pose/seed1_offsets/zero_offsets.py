"""Copy an avatar directory with some expression actions' colour offsets set to zero:

python zero_offsets.py SRC DST COLUMNS      # COLUMNS: comma-separated action slots (0, 1: blinks; 2: jaw)
"""

import shutil
import sys

from safetensors import safe_open
from safetensors.torch import load_file, save_file

src, dst, columns = sys.argv[1], sys.argv[2], [int(c) for c in sys.argv[3].split(",")]
shutil.rmtree(dst, ignore_errors=True)
shutil.copytree(src, dst)
tensors = load_file(f"{dst}/avatar.safetensors")
with safe_open(f"{dst}/avatar.safetensors", "pt") as f:
    metadata = f.metadata()
tensors["splats.sh0_expression"][:, columns] = 0
save_file(tensors, f"{dst}/avatar.safetensors", metadata=metadata)
