"""The chi^2 tails of :func:`telefringe.fringes.noise._tail` for nu = 1 ... 61 (scans of
4 ... 64 phase steps), as scipy.special computes them, so that a command need not import
scipy.special (with what it imports: ~0.1-0.2 s CPU of a cold ``telefringe reconstruct``).

``TAILS[nu - 1] = (c, F)`` with, exactly (``float.fromhex`` of the hexadecimal form)::

    c = 2.0 * float(scipy.special.gammaincinv(nu / 2.0, 1.0 - TAIL))
    F = float(scipy.special.gammainc(nu / 2.0 + 1.0, c / 2.0))

tests/test_coldstart.py checks every entry against scipy.special bit for bit (written with
scipy 1.17.1); noise._tail computes any other nu, or another TAIL, with scipy.
"""

#: the tail probability the table is for (noise._TAIL)
TAIL = 0.0001

TAILS = tuple((float.fromhex(c), float.fromhex(f)) for c, f in (
    ('0x1.e45fe3a3b14d1p+3', '0x1.ff20b8e4873fap-1'),  # nu = 1
    ('0x1.26bb1bbb55553p+4', '0x1.ff7a2bc8677e1p-1'),  # nu = 2
    ('0x1.51b8600a509e9p+4', '0x1.ff9aad54732ffp-1'),  # nu = 3
    ('0x1.7834316c081fcp+4', '0x1.ffabe2d715c1dp-1'),  # nu = 4
    ('0x1.9bead4ea92962p+4', '0x1.ffb6aef015542p-1'),  # nu = 5
    ('0x1.bdb392de2e5a7p+4', '0x1.ffbe27f3a41f1p-1'),  # nu = 6
    ('0x1.de0a418a03bf8p+4', '0x1.ffc3ab9e055b0p-1'),  # nu = 7
    ('0x1.fd3df6dbead39p+4', '0x1.ffc7ed885dbf7p-1'),  # nu = 8
    ('0x1.0dc27453c148cp+5', '0x1.ffcb53d108807p-1'),  # nu = 9
    ('0x1.1c8319bdd9638p+5', '0x1.ffce1d0578d12p-1'),  # nu = 10
    ('0x1.2aef9695ea30ep+5', '0x1.ffd071b56efbbp-1'),  # nu = 11
    ('0x1.39134257ab706p+5', '0x1.ffd26d642e984p-1'),  # nu = 12
    ('0x1.46f719f9d433ep+5', '0x1.ffd4236cccab6p-1'),  # nu = 13
    ('0x1.54a2623f24721p+5', '0x1.ffd5a1d843c8dp-1'),  # nu = 14
    ('0x1.621b15adf5cb4p+5', '0x1.ffd6f31704948p-1'),  # nu = 15
    ('0x1.6f66317945155p+5', '0x1.ffd81f1871be7p-1'),  # nu = 16
    ('0x1.7c87ecc34d73fp+5', '0x1.ffd92c01e19d8p-1'),  # nu = 17
    ('0x1.8983e13fb9203p+5', '0x1.ffda1eaa00f28p-1'),  # nu = 18
    ('0x1.965d29af913a2p+5', '0x1.ffdafaee2798bp-1'),  # nu = 19
    ('0x1.a3167927c71fep+5', '0x1.ffdbc3eeb0eecp-1'),  # nu = 20
    ('0x1.afb22d1df5e68p+5', '0x1.ffdc7c3a82f8ep-1'),  # nu = 21
    ('0x1.bc325b999c052p+5', '0x1.ffdd25ef03041p-1'),  # nu = 22
    ('0x1.c898de8077bcep+5', '0x1.ffddc2cfeb2b9p-1'),  # nu = 23
    ('0x1.d4e75caef3284p+5', '0x1.ffde54595299cp-1'),  # nu = 24
    ('0x1.e11f515da27e2p+5', '0x1.ffdedbcd7f9a4p-1'),  # nu = 25
    ('0x1.ed42123350175p+5', '0x1.ffdf5a3f9f81ap-1'),  # nu = 26
    ('0x1.f950d44b37fcfp+5', '0x1.ffdfd09c2dc90p-1'),  # nu = 27
    ('0x1.02a65832eda56p+6', '0x1.ffe03faf9b402p-1'),  # nu = 28
    ('0x1.089b53371b89dp+6', '0x1.ffe0a82b9efccp-1'),  # nu = 29
    ('0x1.0e87d039e8383p+6', '0x1.ffe10aab7f0c5p-1'),  # nu = 30
    ('0x1.146c3a9981aebp+6', '0x1.ffe167b78b29fp-1'),  # nu = 31
    ('0x1.1a48f51fd8114p+6', '0x1.ffe1bfc7f5765p-1'),  # nu = 32
    ('0x1.201e5af127edep+6', '0x1.ffe213472ab90p-1'),  # nu = 33
    ('0x1.25ecc05a29277p+6', '0x1.ffe26293c3f73p-1'),  # nu = 34
    ('0x1.2bb4738319369p+6', '0x1.ffe2ae0225671p-1'),  # nu = 35
    ('0x1.3175bd0be0471p+6', '0x1.ffe2f5ddda68ep-1'),  # nu = 36
    ('0x1.3730e094ccf12p+6', '0x1.ffe33a6abadfcp-1'),  # nu = 37
    ('0x1.3ce61d36c6216p+6', '0x1.ffe37be5e3b75p-1'),  # nu = 38
    ('0x1.4295aded555e4p+6', '0x1.ffe3ba868a6cep-1'),  # nu = 39
    ('0x1.483fc9f486304p+6', '0x1.ffe3f67eb1e8ep-1'),  # nu = 40
    ('0x1.4de4a51c451d3p+6', '0x1.ffe42ffbc5c29p-1'),  # nu = 41
    ('0x1.53847012a536bp+6', '0x1.ffe467272013fp-1'),  # nu = 42
    ('0x1.591f58a63bf12p+6', '0x1.ffe49c267d434p-1'),  # nu = 43
    ('0x1.5eb58a0195283p+6', '0x1.ffe4cf1c608cdp-1'),  # nu = 44
    ('0x1.64472ce09b4d3p+6', '0x1.ffe500286b9b2p-1'),  # nu = 45
    ('0x1.69d467c0b00d9p+6', '0x1.ffe52f67ab181p-1'),  # nu = 46
    ('0x1.6f5d5f0c173ffp+6', '0x1.ffe55cf4d9cf0p-1'),  # nu = 47
    ('0x1.74e235413f96dp+6', '0x1.ffe588e89bb77p-1'),  # nu = 48
    ('0x1.7a630b1661ce2p+6', '0x1.ffe5b359b205bp-1'),  # nu = 49
    ('0x1.7fdfff99df0ddp+6', '0x1.ffe5dc5d29362p-1'),  # nu = 50
    ('0x1.8559304fb9af0p+6', '0x1.ffe6040681dfap-1'),  # nu = 51
    ('0x1.8aceb94c7803bp+6', '0x1.ffe62a67d4fc0p-1'),  # nu = 52
    ('0x1.9040b54db6c8ap+6', '0x1.ffe64f91f43b5p-1'),  # nu = 53
    ('0x1.95af3dd0a8796p+6', '0x1.ffe6739486e1ep-1'),  # nu = 54
    ('0x1.9b1a6b26b7538p+6', '0x1.ffe6967e239d9p-1'),  # nu = 55
    ('0x1.a08254887995dp+6', '0x1.ffe6b85c67b19p-1'),  # nu = 56
    ('0x1.a5e7102721f55p+6', '0x1.ffe6d93c0bc8ap-1'),  # nu = 57
    ('0x1.ab48b33c918a8p+6', '0x1.ffe6f928f6b4fp-1'),  # nu = 58
    ('0x1.b0a7521a2c4f8p+6', '0x1.ffe7182e4e5abp-1'),  # nu = 59
    ('0x1.b60300368d99ep+6', '0x1.ffe7365686f9ep-1'),  # nu = 60
    ('0x1.bb5bd03a36e10p+6', '0x1.ffe753ab7105cp-1'),  # nu = 61
))
