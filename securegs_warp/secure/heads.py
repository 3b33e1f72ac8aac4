"""The private decoders of SecureGS (the key): F_o†, F_α†, F_cov†, F_c† and the bit decoder F_b†.

They read the same public anchors as the public heads; nothing of them is in the public release.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ..attacks import mean_neighbour_distance
from ..model import ScaffoldHeads, make_mlp
from ..kept import Kept
from ..model.neural_gaussians import AnchorViewInputs
from .keyed_bits import KeyedBitDecoder

FRAMES = ("anchor", "box")
# Inside the box every anchor is at distance 0 from it; this share of the distance to the box's
# centre orders them without moving anyone outside by more than a thousandth of its distance.
INSIDE_TIE_BREAK = 1e-3
# An anchor record's reach stops this share short of the distance to the entry's nearest other
# anchor, so that no float rounding lets an unmoved neighbour pair with the entry.
REACH_MARGIN = 1e-3
# ``PrivateHeads.start_at`` keeps its points this far inside the box's tanh range (a share of the
# half-extent): at the faces F_o†'s gradient vanishes.
START_INSIDE = 0.95


# The cells of a key's private codes, per axis of the contracted box frame, unless the key names its
# own: fine enough that serving anchors rarely share a cell, and so a code (docs/results.md, "Private
# codes in the key", counts them in trained containers). Coarser cells share codes among
# neighbouring anchors and lose less to moved anchors ("Private codes at 1080p in the garden").
CODE_CELLS = 256


def contract(where: torch.Tensor) -> torch.Tensor:
    """[N, 3]: box-frame positions [N, 3] contracted per axis, u = p / (1 + |p|), into (-1, 1): the
    box's inside spans the middle half, and the serving anchors outside it keep distinct places
    instead of piling onto a border."""
    return where / (1.0 + where.abs())


def farthest_points(points: torch.Tensor, count: int) -> torch.Tensor:
    """[count, 3]: ``count`` of the points [M, 3] spread over them by farthest-point sampling, from
    the one farthest from their mean (deterministic: no random draw)."""
    if not 1 <= count <= len(points):
        raise ValueError(f"cannot pick {count} of {len(points)} points")
    chosen = [int((points - points.mean(0)).norm(dim=1).argmax())]
    distance = (points - points[chosen[0]]).norm(dim=1)
    for _ in range(count - 1):
        chosen.append(int(distance.argmax()))
        distance = torch.minimum(distance, (points - points[chosen[-1]]).norm(dim=1))
    return points[chosen]


class LatentGrid(nn.Module):
    """A key's private latent: a dense grid of features (``grid`` [1, d, r, r, r]) over the box's
    neighbourhood, read trilinearly at each anchor's position and added to the anchor's public
    feature before the private heads decode it (``anchor_source`` of ``decode_rows``). Without it
    the hidden Gaussians' colours, opacities and shapes are functions of the public features alone,
    which the cover's loss shapes; the grid gives the key free parameters near the object without
    putting any in the release (d·r³ floats in the key). Positions are read in the box's frame,
    ``contract``-ed. Zero at the start: the decoding begins as it would without it."""

    def __init__(self, feat_dim: int, resolution: int):
        super().__init__()
        if resolution < 2:
            raise ValueError(f"a latent grid needs a resolution of at least 2, got {resolution}")
        self.resolution = int(resolution)
        self.grid = nn.Parameter(torch.zeros(1, feat_dim, resolution, resolution, resolution))

    def forward(self, where: torch.Tensor) -> torch.Tensor:
        """[N, d]: the latent at box-frame positions where [N, 3] (the box spans [-1, 1]³)."""
        u = contract(where)
        # grid_sample reads (x, y, z) against the grid's (W, H, D) axes.
        sampled = F.grid_sample(self.grid, u[None, :, None, None, :], mode="bilinear", padding_mode="border",
                                align_corners=True)
        return sampled[0, :, :, 0, 0].t()


class AnchorCodes(nn.Module):
    """A key's private per-anchor features: a table of codes (``table`` [rows, d] or, with
    ``scales``, [rows, d + 3]), each anchor reading the row that its cell of ``cells``³ over the
    box's ``contract``-ed neighbourhood hashes to, added to its public feature (the first d columns)
    and to its public log scaling l_v[3:] (the last 3, with ``scales``) before the private heads
    decode it. The latent grid is smooth over space; a code is the anchor's own (anchors of one
    cell, or of cells hashed to one row, share it). It is the key's counterpart of the hidden loss's
    gradient into the public features and scalings (``SecureConfig.hidden_feature_grad``,
    ``hidden_scaling_grad``), which fits the released attributes to the hidden object and so costs
    the cover: with codes those gradients can be 0. The scale part is there because a hidden
    Gaussian's scale is exp(l_v[3:]) · sigmoid(F_cov†): without it, or the scalings' gradient, none
    can outgrow the scale the cover gave its anchor. Anchors keep their positions
    under pruning, so a pruned release reads its survivors' codes as trained. Zero at the start."""

    def __init__(self, feat_dim: int, rows: int, scales: bool = False, cells: int = CODE_CELLS):
        super().__init__()
        if rows < 1:
            raise ValueError(f"a code table needs at least one row, got {rows}")
        if cells < 1:
            raise ValueError(f"codes need at least one cell an axis, got {cells}")
        self.feat_dim, self.cells = feat_dim, int(cells)
        self.table = nn.Parameter(torch.zeros(int(rows), feat_dim + (3 if scales else 0)))

    @property
    def rows(self) -> int:
        return self.table.shape[0]

    @property
    def scales(self) -> bool:
        """Whether the codes add to the anchors' log scalings too."""
        return self.table.shape[1] > self.feat_dim

    def forward(self, where: torch.Tensor) -> torch.Tensor:
        """[N, d] (or [N, d + 3] with ``scales``): the codes of anchors at box-frame positions where [N, 3]."""
        cell = ((contract(where) + 1.0) * (0.5 * self.cells)).floor().long().clamp(0, self.cells - 1)
        # Teschner et al.'s spatial hash (three large primes, XOR-ed).
        row = (cell[:, 0] * 73856093) ^ (cell[:, 1] * 19349663) ^ (cell[:, 2] * 83492791)
        return self.table[row % self.rows]


class PrivateHeads(nn.Module):
    """Private MLPs. ``decoder`` has exactly the public heads' shapes (F_α†, F_cov†, F_c†).

    offset_mlp (F_o†): Linear(d+3, d), ReLU, Linear(d, 3k) — the hidden Gaussians' offsets from the
        blended anchor feature and view direction, so that no hidden offset is stored in the file
        (the paper's hybrid decoupled Gaussian encryption, HDGER). ``None`` in the "w/o HDGER"
        ablation, where the anchors carry explicit hidden offsets instead
        (``AnchorModel.hidden_offsets``; measured by the training scripts, not saved in a release).
    bits (F_b†): a ``KeyedBitDecoder`` derived from ``message``, ``bit_seed`` and ``bit_cell``, never trained —
        per-anchor bit logits; the message is the average over anchors (each anchor votes). Training
        projects the features onto the message after every step; a model trained without this key
        reads as fair coin flips (keyed_bits.py), which is what ``verify`` tests. None without a
        bit payload.
    scale_offsets: hidden offsets are in units of the anchor's offset scale exp(l_v[:3]), as the
        public offsets are. The paper writes x_v + F_o†(...) without l_v; scaling keeps the MLP's
        output range independent of the scene's size and of the anchor's voxel level, which is what
        lets one small MLP place Gaussians for anchors grown at several levels. Switchable.
    frame: where F_o† places the hidden Gaussians.
        "anchor" (the paper): x_v + F_o†(f̂_v, d_vc), near their anchor, so hidden Gaussians need
            anchors on the hidden surface (RDO grows them there: the release shows the shape).
        "box": c + h ⊙ tanh(F_o†(f̂_v, (x_v − c) / h)), anywhere in the key's box (``box``: centre c
            [3] and half-extent h [3], world units; F_o† reads the anchor's position in the box's
            frame instead of the view direction, so the hidden geometry is the same from every view).
            Only the anchors within ``serving_radius`` of the box decode hidden Gaussians; they are
            the cover's own anchors, wherever the cover put them.
    n_hidden: k_hid, hidden Gaussians per anchor (None: the public k).
    width: hidden width of the private MLPs (None: d).
    encoding: in the box frame, F_o† reads the anchor's box position p through L octaves of sines
        and cosines, [p, sin(2^l π p), cos(2^l π p)] for l < L (0: p alone). One hidden layer on raw
        coordinates gives smooth functions of position; the octaves let neighbouring anchors place
        their Gaussians independently, which fine detail needs.
    depth: the number of hidden layers of F_o† (1: Scaffold-GS's Linear, ReLU, Linear).
    latent: in the box frame, the resolution of a ``LatentGrid`` whose value at each anchor's
        position the private heads add to its feature (0: none; the features alone).
    codes: in the box frame, the rows of an ``AnchorCodes`` table whose code for each anchor the
        private heads add to its feature too (0: none).
    code_scales: the codes add to each anchor's log scaling l_v[3:] as well (``AnchorCodes`` scales).
    code_cells: the codes' cells per axis (``AnchorCodes`` cells; a key written before it was
        recorded used CODE_CELLS).
    serving: in the box frame, how many anchors, nearest the box first, decode hidden Gaussians (0:
        every anchor that the view shows). Training keeps ``serving_radius`` (a buffer in the units of
        ``box_distance``, saved in the key) just beyond the serving-th nearest anchor
        (``fix_serving``); decoding reads the radius, not the count, so a release that lost anchors
        decodes with the survivors and no anchor the key never trained is drawn in to make up the
        number (it would paint its own Gaussians into the box).
    recorded: in the box frame, the rows of ``anchor_record`` (0: a key without it, as written before
        it existed): the serving anchors' positions as the release was written
        (``key_state``) and each one's reach. Decoding moves served anchors that an attacker shifted
        (quantised or noisy positions) back onto their records (``register``), so that F_o†, the
        codes and the view directions read the positions they were trained with, and then serves
        the anchors paired with an entry alone (the radius still serves where nothing pairs).
    eps2d: the hidden render's screen-space dilation (``RasterOptions.eps2d``, added to each 2D
        covariance), None: the render options' own. The public render must keep Scaffold-GS's for
        the release to look the same in its viewer; the hidden render is the key holder's alone.
    scale_gain: g ≥ 1, the hidden Gaussians' largest scale as a multiple of their anchor's:
        g · exp(l_v[3:]) · sigmoid(F_cov†) (1: Scaffold-GS's bound). Where the hidden loss moves
        nothing in the release, the anchors' scalings are the cover's, sized for the cover's own
        surfaces; an object's large flat parts then need many small Gaussians and come out blotchy.
        F_cov† starts at sigmoid(0) as before, so a gain starts every hidden Gaussian g times larger
        too. A key written before the gain existed used 1.
    """

    def __init__(self, public: ScaffoldHeads, *, message: str | None = None, bit_seed: str | None = None,
                 bit_cell: float | None = None,
                 offsets: bool = True, scale_offsets: bool = True, hidden: bool = True, frame: str = "anchor",
                 n_hidden: int | None = None, width: int | None = None, serving: int = 0,
                 encoding: int = 0, depth: int = 1, latent: int = 0, codes: int = 0, code_scales: bool = False,
                 code_cells: int = CODE_CELLS, recorded: int = 0,
                 eps2d: float | None = None, scale_gain: float = 1.0):
        super().__init__()
        if eps2d is not None and not 0.0 <= eps2d < math.inf:
            raise ValueError(f"eps2d must be >= 0 and finite, got {eps2d}")
        if not 1.0 <= scale_gain < math.inf:
            raise ValueError(f"scale_gain must be >= 1 and finite, got {scale_gain}")
        if frame not in FRAMES:
            raise ValueError(f"frame must be one of {FRAMES}, got {frame!r}")
        if frame == "box" and not offsets:
            raise ValueError("the box frame places hidden Gaussians with F_o†: it needs offsets=True")
        if encoding < 0 or depth < 1:
            raise ValueError(f"encoding must be >= 0 and depth >= 1, got {encoding} and {depth}")
        if encoding and frame != "box":
            raise ValueError("encoding applies to the box frame's positions: it needs frame='box'")
        if codes and (frame != "box" or not hidden):
            raise ValueError("private codes lie over the box frame's positions and feed the hidden decoder: "
                             "they need frame='box' and hidden=True")
        if code_scales and not codes:
            raise ValueError("code_scales adds the codes to the anchors' scalings: it needs codes (rows >= 1)")
        if latent and (frame != "box" or not hidden):
            raise ValueError("a latent grid lies over the box frame's positions and feeds the hidden decoder: "
                             "it needs frame='box' and hidden=True")
        d = public.feat_dim
        k = public.n_offsets if n_hidden is None else int(n_hidden)
        w = d if width is None else int(width)
        self.feat_dim, self.n_offsets, self.scale_offsets = d, k, scale_offsets
        self.frame, self.width, self.serving = frame, w, int(serving)
        self.encoding, self.depth = int(encoding), int(depth)
        self.eps2d = None if eps2d is None else float(eps2d)
        self.scale_gain = float(scale_gain)
        self.decoder = ScaffoldHeads(d, k, use_feat_bank=public.use_feat_bank,
                                     add_opacity_dist=public.add_opacity_dist, add_cov_dist=public.add_cov_dist,
                                     add_color_dist=public.add_color_dist, width=w) if hidden else None
        self.offset_mlp = make_mlp(d + 3 * (1 + 2 * self.encoding), w, 3 * k, depth=self.depth) \
            if hidden and offsets else None
        self.latent_grid = LatentGrid(d, latent) if latent else None
        self.codes = AnchorCodes(d, codes, scales=code_scales, cells=code_cells) if codes else None
        if frame == "box":  # set by the trainer from the hidden object's bounds; saved in the key
            self.register_buffer("box", torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]))
            self.register_buffer("serving_radius", torch.tensor(float("inf")))
        if recorded:
            if not self.serves_by_radius:
                raise ValueError("an anchor record holds a box frame's serving anchors: it needs frame='box' "
                                 "and serving >= 1")
            self.register_buffer("anchor_record", torch.zeros(int(recorded), 4))
        self._registration = Kept()  # the last ``register``, while positions, record and box are unchanged
        self.bits = None
        self.set_message(message, bit_seed, bit_cell)
        self._serving = Kept()  # the last serving_mask, while positions, radius and box are unchanged
        self._serving_index = Kept()  # its indices, while it is the same mask

    def set_message(self, message: str | None, bit_seed: str | None, bit_cell: float | None) -> None:
        """(Re)derive the bit decoder (on the CPU) from the message (L characters 0/1), its seed (hex)
        and its cell edge (scene units)."""
        if not (message is None) == (bit_seed is None) == (bit_cell is None):
            raise ValueError("a bit payload needs its message, its decoder's seed and its cell edge (bit_cell)")
        self.bits = None if message is None else KeyedBitDecoder(self.feat_dim, message, bit_seed, bit_cell)

    @property
    def n_bits(self) -> int:
        return 0 if self.bits is None else self.bits.n_bits

    def hidden_offsets(self, inputs: AnchorViewInputs) -> torch.Tensor:
        """World-space displacements [Nv, k_hid, 3] of the hidden Gaussians of the decoded anchors."""
        if self.frame == "box":
            centre, half = self.box[0], self.box[1]
            where = self.box_position(inputs.xyz)
            raw = self.offset_mlp(torch.cat([inputs.feat, self.encode(where)], dim=1)).view(-1, self.n_offsets, 3)
            return centre + half * torch.tanh(raw) - inputs.xyz[:, None, :].detach()
        raw = self.offset_mlp(torch.cat([inputs.feat, inputs.ob_view], dim=1)).view(-1, self.n_offsets, 3)
        return raw * inputs.scaling[:, None, :3] if self.scale_offsets else raw

    @torch.no_grad()
    def start_at(self, points: torch.Tensor) -> None:
        """Box frame: set F_o†'s last bias so that hidden Gaussian j of every anchor starts at
        points[j] ([k_hid, 3], world units, inside the box), where F_o†'s default initialisation
        starts them all near the box's centre. The rest of F_o†'s initial weights scatters each
        slot's Gaussians around its point, anchor by anchor."""
        if self.frame != "box" or self.offset_mlp is None:
            raise ValueError("start_at places the box frame's hidden Gaussians: it needs frame='box' and F_o†")
        if points.shape != (self.n_offsets, 3):
            raise ValueError(f"start_at needs one point per hidden Gaussian of an anchor, [{self.n_offsets}, 3]; "
                             f"got {list(points.shape)}")
        # Inside the box's tanh range, short of the saturated faces.
        inside = ((points.to(self.box) - self.box[0]) / self.box[1]).clamp(-START_INSIDE, START_INSIDE)
        self.offset_mlp[-1].bias.copy_(torch.atanh(inside).reshape(-1))

    @property
    def anchor_source(self):
        """The ``AnchorSource`` of the hidden decoding: the public features plus the latent grid's
        and the codes' values at each anchor, the public log scalings plus the codes' scale part and
        log(scale_gain) (None with neither grid nor codes and a gain of 1)."""
        if self.latent_grid is None and self.codes is None and self.scale_gain == 1.0:
            return None
        return self._private_inputs

    def _private_inputs(self, xyz: torch.Tensor, feat: torch.Tensor,
                        log_scaling: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Features [Nv, d] and log scalings [Nv, 6] of anchors at positions xyz [Nv, 3], with the
        grid's and the codes' values added, and log(scale_gain) to the Gaussians' part l_v[3:]."""
        # What adds to l_v[3:]: log(scale_gain) (a number) and the codes' scale part ([Nv, 3]).
        scale_shifts = [math.log(self.scale_gain)] if self.scale_gain != 1.0 else []
        where = None if self.latent_grid is None and self.codes is None else self.box_position(xyz)
        if self.latent_grid is not None:
            feat = feat + self.latent_grid(where)
        if self.codes is not None:
            code = self.codes(where)
            feat = feat + code[:, :self.feat_dim]
            if self.codes.scales:
                scale_shifts.append(code[:, self.feat_dim:])
        if scale_shifts:
            log_scaling = torch.cat([log_scaling[:, :3], log_scaling[:, 3:] + sum(scale_shifts)], dim=1)
        return feat, log_scaling

    def box_position(self, xyz: torch.Tensor) -> torch.Tensor:
        """[N, 3]: anchor positions [N, 3] in the box's frame (the box spans [-1, 1]³); no gradient
        to the positions."""
        return (xyz.detach() - self.box[0]) / self.box[1]

    def encode(self, where: torch.Tensor) -> torch.Tensor:
        """[N, 3(1 + 2L)]: box positions [N, 3] and their L octaves of sines and cosines."""
        if not self.encoding:
            return where
        angles = where[:, None, :] * (math.pi * 2.0 ** torch.arange(self.encoding, device=where.device))[None, :, None]
        return torch.cat([where, torch.sin(angles).flatten(1), torch.cos(angles).flatten(1)], dim=1)

    def set_box(self, lo, hi) -> None:
        """The box frame's region: corners ``lo``, ``hi`` [3] in world units."""
        lo, hi = (torch.as_tensor(v, dtype=torch.float32, device=self.box.device) for v in (lo, hi))
        self.box.copy_(torch.stack([0.5 * (lo + hi), (0.5 * (hi - lo)).clamp_min(1e-6)]))

    @property
    def serves_by_radius(self) -> bool:
        """Whether only the anchors within ``serving_radius`` decode (box frame, ``serving`` > 0)."""
        return self.frame == "box" and self.serving > 0

    def box_distance(self, xyz: torch.Tensor) -> torch.Tensor:
        """[N] how far anchor positions [N, 3] are from the box: the distance to it, plus
        INSIDE_TIE_BREAK times the distance to its centre, so that anchors inside the box (all at
        distance 0 from it) rank nearest the centre first and ``serving`` stays a count there."""
        outside = ((xyz - self.box[0]).abs() - self.box[1]).clamp_min(0.0).norm(dim=1)
        return outside + INSIDE_TIE_BREAK * (xyz - self.box[0]).norm(dim=1)

    @torch.no_grad()
    def fix_serving(self, xyz: torch.Tensor) -> None:
        """Set ``serving_radius`` so that the ``serving`` anchors nearest the box, of the anchor
        positions [N, 3] being trained, decode (with any tied with the last; all of them when there
        are fewer). The radius lies halfway between the last serving anchor and the next one out,
        so that rounding (another device, a float16 round trip) does not move an anchor across it.
        Nothing to do outside the box frame or with ``serving`` 0."""
        if not self.serves_by_radius:
            return
        distance = self.box_distance(xyz)
        if len(distance) <= self.serving:
            self.serving_radius.fill_(float("inf"))
            return
        last = distance.kthvalue(self.serving).values
        beyond = torch.where(distance > last, distance, torch.full_like(distance, float("inf"))).min()
        self.serving_radius.copy_(0.5 * (last + beyond))

    @torch.no_grad()
    def serving_mask(self, xyz: torch.Tensor) -> torch.Tensor | None:
        """[N] bool, the anchors that decode hidden Gaussians in the box frame: those within
        ``serving_radius`` of the box, from anchor positions [N, 3]; None in the anchor frame or
        with ``serving`` 0 (the view's visible anchors decode)."""
        if not self.serves_by_radius:
            return None
        # Training renders the same anchors every step: the mask is kept while they, the radius and
        # the box are unchanged.
        return self._serving.get((xyz, self.serving_radius, self.box),
                                 lambda: self.box_distance(xyz) <= self.serving_radius)

    def key_state(self, xyz: torch.Tensor) -> tuple[dict, dict]:
        """(tensors, description): what a key of these heads holds for a release whose anchors lie
        at xyz [N, 3]: the state dict and ``describe()``, with, in the box frame, ``anchor_record``
        [S, 4]: the positions of the S anchors that serve there and each one's reach, its distance
        to the nearest other anchor of the release (REACH_MARGIN short of it)."""
        tensors = {name: value.detach() for name, value in self.state_dict().items()}
        described = self.describe()
        if self.serves_by_radius:
            mask = self.serving_mask(xyz)
            served = xyz[mask].detach()
            reach = (1.0 - REACH_MARGIN) * mean_neighbour_distance(xyz, 1)[mask].to(served.dtype)
            tensors["anchor_record"] = torch.cat([served, reach[:, None]], dim=1)
            described["recorded"] = len(served)
        return tensors, described

    @torch.no_grad()
    def register(self, xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(positions [N, 3], rows [P] long ascending or None): anchor positions xyz [N, 3] with
        anchors moved back onto the entries of ``anchor_record``, and the anchors paired with an
        entry, which alone then serve. Pairs of an anchor and an entry closer than the entry's reach
        are taken nearest first, each anchor and each entry once. An anchor shifted by less than half
        its reach (an attacker's small move, a quantisation) is always given back to its own entry,
        since every other pair it or its entry could form is longer; larger shifts are taken back as
        far as the pairs stay unambiguous, and no unmoved anchor is ever taken by another's entry,
        whose reach stops short of it.

        Serving the paired anchors alone keeps out the anchors the key never served that the attack
        moved into the serving radius (they would paint their Gaussians into the box) and the
        recorded ones moved beyond their reach (decoded at a wrong position, they do more harm than
        their absence, which robust training's dropout prepares for). Where the pairs are the anchors
        within the serving radius and none is off its entry (an unattacked or a pruned release), where
        nothing pairs, or where the key holds no record, it is (xyz itself, None): the radius decides,
        as it does without a record. Only anchors within the serving radius plus the largest reach
        are looked at."""
        record = getattr(self, "anchor_record", None)
        if record is None or not len(record):
            return xyz, None
        return self._registration.get((xyz, record, self.box, self.serving_radius),
                                      lambda: self._register(xyz, record))

    def _register(self, xyz: torch.Tensor, record: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        where, reach = record[:, :3], record[:, 3]
        near = (self.box_distance(xyz) <= self.serving_radius + reach.max()).nonzero()[:, 0]
        distance = torch.cdist(xyz[near], where, compute_mode="donot_use_mm_for_euclid_dist")  # [Nn, S]
        # An anchor on an entry always pairs with it, even where the reach is 0 (two anchors at one place).
        anchor, entry = ((distance < reach[None]) | (distance == 0)).nonzero(as_tuple=True)
        order = distance[anchor, entry].argsort()
        pairs, used_anchors, used_entries = [], set(), set()
        for a, e in zip(anchor[order].tolist(), entry[order].tolist()):  # greedy, nearest pairs first
            if a not in used_anchors and e not in used_entries:
                used_anchors.add(a)
                used_entries.add(e)
                pairs.append((a, e))
        if not pairs:  # every anchor moved beyond reach, or none near: nothing to take back
            return xyz, None
        taken = torch.tensor(pairs, device=xyz.device)
        rows, entries = near[taken[:, 0]], taken[:, 1]
        if torch.equal(xyz[rows], where[entries]):
            inside = self.serving_mask(xyz)
            if int(inside.sum()) == len(rows) and bool(inside[rows].all()):
                return xyz, None
            return xyz, rows.sort().values  # on their entries, but another anchor was moved inside the radius
        moved = xyz.clone()
        moved[rows] = where[entries]
        return moved, rows.sort().values

    @torch.no_grad()
    def nearest_serving(self, xyz: torch.Tensor, count: int) -> torch.Tensor:
        """[count] long, ascending: the indices of the ``count`` anchor positions of xyz [N, 3]
        nearest the box (``box_distance``), found on the device without a host read."""
        return self.box_distance(xyz).topk(count, largest=False).indices.sort().values

    @torch.no_grad()
    def serving_index(self, xyz: torch.Tensor) -> torch.Tensor | None:
        """[Ns] long, the indices of ``serving_mask``'s True entries (None where it is None), kept
        with the mask: their host read (a count) is made once per refit, not once per render."""
        mask = self.serving_mask(xyz)
        return None if mask is None else self._serving_index.get((mask,), lambda: mask.nonzero()[:, 0])

    def bit_logits(self, feat: torch.Tensor, xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-anchor bit logits [N] and the bit each anchor votes on [N] (int64), from anchor
        features [N, d] at positions [N, 3] (see ``KeyedBitDecoder``)."""
        return self.bits(feat, xyz)

    @torch.no_grad()
    def decode_bits(self, feat: torch.Tensor, xyz: torch.Tensor) -> torch.Tensor:
        """The message [L] (0/1 ints): each anchor votes on its bit with its logit's sign, the
        majority decides (``KeyedBitDecoder.vote``; a bit no anchor votes on reads 0)."""
        return (self.bits.vote(feat, xyz)[0] > 0.5).to(torch.int64)

    def named_mlps(self) -> dict[str, nn.Module]:
        """Trainable parts by learning-rate schedule: the MLPs (the decoder's names are the public
        ones), the latent grid ("latent") and the codes ("codes")."""
        parts = dict(self.decoder.named_mlps()) if self.decoder is not None else {}
        if self.offset_mlp is not None:
            parts["mlp_offset"] = self.offset_mlp
        if self.latent_grid is not None:
            parts["latent"] = self.latent_grid
        if self.codes is not None:
            parts["codes"] = self.codes
        return parts

    def describe(self) -> dict:
        """The constructor arguments, for the key's metadata."""
        bits = {} if self.bits is None else {"message": self.bits.message, "bit_seed": self.bits.seed,
                                           "bit_cell": self.bits.cell}
        return {**bits, "offsets": self.offset_mlp is not None, "scale_offsets": self.scale_offsets,
                "hidden": self.decoder is not None, "frame": self.frame, "n_hidden": self.n_offsets,
                "width": self.width, "serving": self.serving, "encoding": self.encoding, "depth": self.depth,
                "latent": 0 if self.latent_grid is None else self.latent_grid.resolution,
                "codes": 0 if self.codes is None else self.codes.rows,
                "code_scales": self.codes is not None and self.codes.scales,
                "code_cells": CODE_CELLS if self.codes is None else self.codes.cells,
                "recorded": len(getattr(self, "anchor_record", ())), "eps2d": self.eps2d,
                "scale_gain": self.scale_gain}
