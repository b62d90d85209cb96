import synthbos

# Render a small image pair with its ray-traced truth, then add 1 % sensor noise (of the dot peak)
pair = synthbos.render_pair({"camera": {"pixels": [128, 128]}, "rays": {"per_dot": 200}})
reference, gradient = synthbos.add_noise(pair, noise_percent=1.0, seed=0)

# Track every dot from where the camera model puts it (the nominal prior): one row per pair dot
table = synthbos.track_pair(reference, gradient, prior_xy=synthbos.nominal_prior(pair))

# Score against the truth: displacement error percentiles (px) and the yield of valid dots
print(synthbos.score(pair, table))

# Integrate the displacements to the depth-averaged density (kg/m^3) on a grid at the mid-plane
density = synthbos.integrate(table, pair)
print(density.density.shape, density.reference)

# The table as a pandas DataFrame: one row per dot, its dot_id, every field a column
df = synthbos.to_dataframe(table)
print(df[df.valid][["dot_id", "x", "y", "u", "v"]].describe())
