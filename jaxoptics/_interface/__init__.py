"""Single-interface kernels: Fresnel reflectance and transmittance, real and complex amplitudes,
Schlick's approximations (`_fresnel`, with its terms and their derivatives in
`_fresnel_terms`); reflected and refracted directions, critical and Brewster angles
(`_refract`).

May import: `_core`.
"""
