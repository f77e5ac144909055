"""How many of Anny's bones each template vertex's skinning weights use: the outputs of the weight
MLP's last layer that matter for a Gaussian (the others get ~1e-8 after the softmax with
log(w + 1e-8)). ``python bone_support.py`` prints a Markdown table."""

from eva_engine.body import load_body_model

weights = load_body_model("anny").skinning_weights  # [V, J]
rows = [("> 0", weights > 0), ("> 1e-3", weights > 1e-3)]
print(f"Anny: {weights.shape[0]} vertices, {weights.shape[1]} bones\n")
print("| bones counted | per vertex, max | mean | vertices with at most 4 |")
print("|---|---:|---:|---:|")
for name, used in rows:
    count = used.sum(dim=1)
    share = float((count <= 4).float().mean())
    print(f"| weight {name} | {int(count.max())} | {float(count.float().mean()):.2f} | {share:.1%} |")
