"""Cell-list neighbour search equals brute force exactly (property-based)."""
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchsph.core.neighbors import Domain, brute_force_pairs, build_pairs, build_table
from torchsph.core.verlet import VerletList, subset_table


def as_set(i, j):
    return set(zip(i.tolist(), j.tolist()))


@st.composite
def clouds(draw):
    dim = draw(st.sampled_from([2, 3]))
    n = draw(st.integers(1, 150 if dim == 2 else 120))
    radius = draw(st.floats(0.05, 0.3))
    periodic = [draw(st.booleans()) for _ in range(dim)]
    lengths = [draw(st.floats(2.0 * radius * (1 + 1e-9), 1.5)) for _ in range(dim)]
    lo = [draw(st.floats(-1.0, 1.0)) for _ in range(dim)]
    seed = draw(st.integers(0, 2**31 - 1))
    clustered = draw(st.booleans())
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, dim, generator=g, dtype=torch.float64)
    if clustered:  # many coincident-ish points and particles in few cells
        u = (u * 4).floor() / 4 + 0.01 * u
    x = torch.tensor(lo, dtype=torch.float64) + u * torch.tensor(lengths, dtype=torch.float64)
    # open axes: some particles outside the nominal box too
    for a in range(dim):
        if not periodic[a]:
            x[:, a] = x[:, a] * draw(st.floats(0.5, 3.0))
    hi = [l + L for l, L in zip(lo, lengths)]
    return x, radius, Domain(lo, hi, periodic)


@settings(max_examples=200, deadline=None)
@given(clouds(), st.sampled_from([1, 2, 3]))
def test_cell_list_equals_brute_force(c, cells_per_radius):
    """Cells of edge radius / m (m = 1, 2, 3: 3, 5, 7 cells a stencil side, trimmed to the
    sphere for m = 3), the inner axis's run in one range, on open and periodic axes."""
    x, radius, dom = c
    i, j = build_pairs(x, radius, dom, cells_per_radius)
    bi, bj = brute_force_pairs(x, radius, dom)
    got, ref = as_set(i, j), as_set(bi, bj)
    assert got == ref
    assert len(got) == i.numel()  # no duplicates
    assert torch.all(i[1:] >= i[:-1])  # sorted by i


@settings(max_examples=100, deadline=None)
@given(clouds(), st.integers(0, 2**31 - 1))
def test_grouped_passes_give_the_table_of_one_pass_at_a_time(c, seed):
    """The stencil's passes searched in groups (all at once for few rows) give exactly the
    table, order within rows included, that one pass at a time gives; so do the cells' runs
    found by binary search instead of read from the cells' start table; and a table of some
    rows (a partial rebuild's) is those rows of the whole table."""
    from torchsph.core import neighbors

    x, radius, dom = c
    rows = torch.randperm(x.shape[0], generator=torch.Generator().manual_seed(seed))[: max(1, x.shape[0] // 3)]
    grouped = build_table(x, radius, dom), build_table(x, radius, dom, rows=rows)
    saved = neighbors.PASS_ROWS, neighbors.DENSE_CELLS
    try:
        neighbors.PASS_ROWS = 1  # one pass per group
        single = build_table(x, radius, dom), build_table(x, radius, dom, rows=rows)
        neighbors.PASS_ROWS, neighbors.DENSE_CELLS = saved[0], 0  # binary searches of the sorted cells
        searched = build_table(x, radius, dom), build_table(x, radius, dom, rows=rows)
    finally:
        neighbors.PASS_ROWS, neighbors.DENSE_CELLS = saved
    for a, b, s in zip(grouped, single, searched):
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
        assert torch.equal(a[0], s[0]) and torch.equal(a[1], s[1])
    nb, mask = grouped[0]
    k = grouped[1][0].shape[1]
    assert torch.equal(grouped[1][0], nb[rows, :k]) and torch.equal(grouped[1][1], mask[rows, :k])


def test_periodic_wraps_across_faces():
    dom = Domain([0.0, 0.0], [1.0, 1.0], [True, False])
    x = torch.tensor([[0.01, 0.5], [0.99, 0.5], [0.5, 0.5]], dtype=torch.float64)
    i, j = build_pairs(x, 0.05, dom)
    assert as_set(i, j) == {(0, 1), (1, 0)}


def test_table_padding_is_self():
    dom = Domain([0.0, 0.0], [1.0, 1.0], [False, False])
    x = torch.tensor([[0.1, 0.1], [0.15, 0.1], [0.9, 0.9]], dtype=torch.float64)
    nb, mask = build_table(x, 0.1, dom)
    assert nb.shape == (3, 1)
    assert nb[2, 0] == 2 and not mask[2, 0]
    assert nb[0, 0] == 1 and mask[0, 0]


def test_verlet_list_rebuilds_when_a_pair_may_have_changed_by_a_skin():
    """The rebuild test bounds the change of every pair's separation by the smaller of
    2 max |d| and the diagonal of the box of the displacements and 0: one particle that moved
    a skin, two that moved half a skin apart, or all of them moving together a skin (the box
    holds 0: a particle at rest might not have been checked) are due; less is not."""
    dom = Domain([0.0, 0.0], [1.0, 1.0], [True, True])
    x = torch.rand(200, 2, dtype=torch.float64)
    vl = VerletList(0.1, 0.02, dom)
    assert vl.update(x)
    e = torch.tensor([1.0, 0.0], dtype=torch.float64)
    assert not vl.update(x + 0.0199 * e)  # all together: no pair changed
    assert vl.needs_rebuild(x + 0.0201 * e)
    one = x.clone()
    one[0] += 0.0199 * e
    assert not vl.update(one)  # one fast particle: its pairs changed by 0.0199 < skin
    one[0] += 0.0002 * e
    assert vl.needs_rebuild(one)
    two = x.clone()
    two[0] += 0.0099 * e
    two[1] -= 0.0099 * e
    assert not vl.update(two)
    two[1] -= 0.0002 * e
    assert vl.update(two)  # 0.0101 each way: their separation may have changed by 0.0202
    # pairs of the Verlet list cover every pair within the cut-off after small motion
    x3 = two + 0.004 * torch.randn_like(two).clamp(-1, 1)
    i, j = brute_force_pairs(x3, 0.1, dom)
    nb, mask = vl.nb, vl.mask
    have = {(a, int(b)) for a in range(200) for b, m in zip(nb[a], mask[a]) if m}
    assert as_set(i, j) <= have


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.0, 1.0), st.booleans())
def test_no_rebuild_means_no_pair_changed_by_more_than_the_skin(seed, spread, blob):
    """Whenever the test says no rebuild, every pair's separation changed by at most the skin
    (brute force over all pairs), for random motion: a blob moving as one past particles at
    rest, plus random scatter of size ``spread`` (in skins)."""
    g = torch.Generator().manual_seed(seed)
    dom = Domain([0.0] * 3, [1.0] * 3, [False] * 3)
    x = torch.rand(60, 3, dtype=torch.float64, generator=g)
    skin = 0.05
    vl = VerletList(0.1, skin, dom)
    vl.update(x)
    d = spread * skin * (2 * torch.rand(60, 3, dtype=torch.float64, generator=g) - 1)
    if blob:
        d[:30] += skin * torch.rand(3, dtype=torch.float64, generator=g)
    worst = float((d.unsqueeze(0) - d.unsqueeze(1)).norm(dim=-1).max())
    if not vl.needs_rebuild(x + d):
        assert worst <= skin * (1 + 1e-12)
    assert vl.needs_rebuild(x + d) == (min(2 * float(d.norm(dim=-1).max()), float(
        (d.amax(0).clamp_min(0) - d.amin(0).clamp_max(0)).norm())) > skin)


def test_lattice_with_radius_a_multiple_of_the_spacing():
    """A particle lattice (every particle on a cell face when the radius is a multiple of the
    spacing, as in the scenes: radius 3.5 dx) and lattice distances just inside and just
    outside the radius."""
    dx = 2.5e-4
    g = torch.arange(8, dtype=torch.float64) * dx
    x = torch.stack(torch.meshgrid(g, g, g[:5], indexing="ij"), -1).reshape(-1, 3)
    dom = Domain([0.0] * 3, [1.0] * 3, [False] * 3)
    ref = as_set(*brute_force_pairs(x, 3.5 * dx, dom))
    for m in (1, 2, 3):
        for radius in (3.5 * dx, 3.0 * dx * (1 + 1e-9), 3.0 * dx * (1 - 1e-9), 2.0 * dx * (1 + 1e-9)):
            assert as_set(*build_pairs(x, radius, dom, m)) == as_set(*brute_force_pairs(x, radius, dom))
    assert len(ref) > 0


def table_pairs(nb, mask):
    i = torch.arange(nb.shape[0]).unsqueeze(1).expand_as(nb)[mask]
    return as_set(i, nb[mask])


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.booleans(), st.booleans(), st.booleans())
def test_partial_rebuild_holds_exactly_the_pairs_of_a_full_build(seed, with_work, periodic, rod):
    """A rigid lattice block translating, melt particles moving fast over and into it, block
    particles melting away (and moving on as melt), one refreezing in a new place, one moved
    off the lattice between two rebuilds (melted and refrozen unseen), the work set changing,
    and (``rod``) a second rigid body, a lattice rod fed down into the block as a wire is (its
    own group: its pairs with the block found across the groups): after every rebuild the
    partial table holds exactly the pairs of a full build over the same work set; most
    rebuilds are partial; rows hold no duplicates."""
    g = torch.Generator().manual_seed(seed)
    dx = 0.1
    a = torch.arange(10, dtype=torch.float64) * dx
    block = torch.stack(torch.meshgrid(a, a, a[:4], indexing="ij"), -1).reshape(-1, 3)
    melt = torch.rand(60, 3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 1.0, 0.4]) \
        + torch.tensor([0.0, 0.0, 0.3])
    parts = [block, melt]
    if rod:  # 3 x 3 x 8 lattice columns, their foot 1.5 dx above the block's top at a slant
        b3 = torch.arange(3, dtype=torch.float64) * dx
        rod_x = torch.stack(torch.meshgrid(b3, b3, torch.arange(8, dtype=torch.float64) * dx, indexing="ij"), -1)
        parts.append(rod_x.reshape(-1, 3) + torch.tensor([0.42, 0.37, 0.45], dtype=torch.float64))
    x = torch.cat(parts)
    nblk, N = block.shape[0], x.shape[0]
    body = torch.full((N,), -1, dtype=torch.long)
    body[:nblk] = 1
    v = torch.zeros(N, 3, dtype=torch.float64)
    v[:nblk] = torch.tensor([0.013, -0.004, 0.0], dtype=torch.float64)
    v[nblk:nblk + 60] = 0.05 * torch.randn(60, 3, generator=g, dtype=torch.float64)
    if rod:
        body[nblk + 60:] = 2
        v[nblk + 60:] = torch.tensor([0.011, -0.004, -0.021], dtype=torch.float64)
    dom = Domain([-0.5, -0.5, -0.5], [1.5, 1.5, 1.5], [periodic, False, False])
    radius, skin = 2.0 * dx, 0.05
    vl = VerletList(radius, skin, dom)
    work = torch.ones(N, dtype=torch.bool)
    builds = 0
    for step in range(60):
        x = dom.wrap(x + v)
        if step == 10:  # block particles near the top melt and move off
            top = torch.nonzero((body == 1) & (x[:, 2] > x[:nblk, 2].max() - 1e-9)).squeeze(1)[:15]
            body[top] = -1
            v[top] = 0.05 * torch.randn(top.numel(), 3, generator=g, dtype=torch.float64)
        if step == 30:  # one of them refreezes (joins the body's motion) somewhere else
            body[top[0]] = 1
            v[top[0]] = v[0]
        if rod and step == 40:  # the rod's lowest particles weld to the block (join its body and motion)
            foot = nblk + 60 + torch.nonzero(x[nblk + 60:, 2] < x[nblk + 60:, 2].min() + 1e-9).squeeze(1)
            body[foot] = 1
            v[foot] = v[0].clone()
            # a body particle that melted, moved and refroze between two rebuilds
            x[nblk // 2] += torch.tensor([0.02, 0.015, 0.0], dtype=torch.float64)
        if with_work and step % 7 == 3:  # the work set changes (heat spreads, cold solid leaves)
            work = torch.rand(N, generator=g) > 0.2
            work[nblk:] = True
        sub = (lambda: work) if with_work else None
        if vl.update(x, subset=sub, rigid=lambda: body.clone() if rod else body >= 0):
            builds += 1
            ref_nb, ref_mask = (subset_table(x, work, radius + skin, dom).to_dense() if with_work
                                else build_table(x, radius + skin, dom))
            nb, mask = vl.nb, vl.mask
            got = table_pairs(nb, mask)
            assert got == table_pairs(ref_nb, ref_mask)
            assert len(got) == int(mask.sum())  # no duplicates
            assert torch.all(nb[~mask] == torch.arange(N).unsqueeze(1).expand_as(nb)[~mask])
            if with_work:  # the table holds the working particles' rows only
                assert torch.equal(vl.table.rows, torch.nonzero(work).squeeze(1))
    assert builds >= 10
    assert vl.n_partial >= builds // 2


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([2, 3]), st.floats(0.02, 0.3))
def test_active_set_dilation_holds_every_particle_within_the_radius(seed, dim, radius):
    """The active set's dilation (torchsph/step/active.py): every particle within ``radius`` of a
    seed is taken in (brute force), none beyond (1 + 1/k) sqrt(dim) radius (k voxels per radius:
    each axis's reach); the dense voxel grid (running sums) and the sparse voxel keys give the same set."""
    import torchsph.step.active as A

    g = torch.Generator().manual_seed(seed)
    x = torch.rand(400, dim, generator=g, dtype=torch.float64) * torch.tensor([1.0, 0.7, 0.4][:dim])
    seed_mask = torch.rand(400, generator=g) < 0.05
    dense = A.dilate(x, seed_mask, radius)
    old = A.DENSE_VOXELS
    try:
        A.DENSE_VOXELS = 0
        sparse = A.dilate(x, seed_mask, radius)
    finally:
        A.DENSE_VOXELS = old
    assert torch.equal(dense, sparse)
    if seed_mask.any():
        d = torch.cdist(x, x[seed_mask]).min(1).values
        assert bool(dense[d < radius].all())
        assert not bool(dense[d > (1.0 + 1.0 / A.VOXELS_PER_RADIUS) * radius * dim ** 0.5].any())
    else:
        assert not bool(dense.any())


def test_a_trimmed_gather_holds_the_same_pairs_in_fewer_columns():
    """A lattice with a packed blob (16x the density: its rows are ~4x as wide as the
    lattice's): the rows far from the blob, gathered with ``trim``, come in at most 3/4 of the
    table's width, a multiple of 8, with exactly the pairs of the untrimmed gather (every
    dropped column is padding in all of them); rows that need the full width keep it."""
    from torchsph.core.neighbors import NeighbourTable

    g = torch.linspace(0.0, 1.0, 41, dtype=torch.float64)
    lattice = torch.cartesian_prod(g, g)
    blob = 0.1 + 0.0625 * torch.rand(400, 2, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    x = torch.cat([lattice, blob])
    dom = Domain(lo=(-1.0, -1.0), hi=(2.0, 2.0), periodic=(False, False))
    T = NeighbourTable.dense(*build_table(x, 0.06, dom))
    far = torch.nonzero((x[:, 0] > 0.5) & (x[:, 1] > 0.5)).squeeze(1)
    nb, mask = T.gather(far, within=True)
    nb_t, mask_t = T.gather(far, within=True, trim=True)
    assert nb_t.shape[1] <= 0.75 * T.k and nb_t.shape[1] % 8 == 0
    pairs = lambda nb, m: set(zip(far.unsqueeze(1).expand_as(nb)[m].tolist(), nb[m].tolist()))  # noqa: E731
    assert pairs(nb_t, mask_t) == pairs(nb, mask) and mask_t.sum() > 0
    near = torch.arange(x.shape[0] - 400, x.shape[0])  # the blob's own rows: the table is theirs
    assert T.gather(near, within=True, trim=True)[0].shape[1] == T.k
