"""Reference logits of every shipped checkpoint on fixed CHW frames (made with the CHW code, commit bc21b44)."""
import torch
from spf_rl.checkpoint import load_checkpoint
from spf_rl.modules.registry import build_policy
from tensordict import TensorDict
from torchrl.modules import set_recurrent_mode
g = torch.Generator().manual_seed(1234)
B, T, n, S = 2, 4, 30, 64
pixels = torch.randint(0, 256, (B, T, 3, S, S), dtype=torch.uint8, generator=g)
demo_frames = torch.randint(0, 256, (B, 1, n, 3, S, S), dtype=torch.uint8, generator=g).expand(B, T, n, 3, S, S).contiguous()
demo_actions = torch.randint(0, 3, (B, 1, n), generator=g).expand(B, T, n).contiguous()
is_init = torch.zeros(B, T, 1, dtype=torch.bool); is_init[:, 0] = True
out = {"seed": 1234}
import glob
for path in sorted(glob.glob("checkpoints/*.pt")):
    ck = load_checkpoint(path)
    policy = build_policy(ck["model_type"], ck["model_config"]).eval()
    policy.load_state_dict(ck["model"])
    td = TensorDict({"pixels": pixels, "demo_frames": demo_frames, "demo_actions": demo_actions, "is_init": is_init}, [B, T])
    # every row's state: zeros, sequence mode starts from is_init
    prim = policy.make_tensordict_primer()
    for k, spec in prim.primers.items(True, True):
        td.set(k, spec.zero((B, T)))
    with torch.no_grad(), set_recurrent_mode(True):
        res = policy(td)
    name = path.split("/")[-1][:-3]
    out[f"logits/{name}"] = res["logits"].clone()
    print(name, res["logits"].shape, ck["model_type"])
torch.save(out, "tests/data/reference_logits.pt")
